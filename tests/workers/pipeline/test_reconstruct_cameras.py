"""The reconstruct stage's cameras: the numpy forms of the shared cameras.json types, and
its output read back by the compare stage."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tests.app.formats.test_cameras import PARAMS, PINHOLE, pose
from workers.pipeline.compare.files import load_cameras
from workers.pipeline.errors import InputError
from workers.pipeline.geometry import invert_rigid
from workers.pipeline.reconstruct.cameras import (
    CameraView,
    Intrinsics,
    intrinsics_from_colmap,
    parse_cameras,
    write_cameras,
)
from workers.pipeline.reconstruct.cameras import (
    load_cameras as load_reconstruct_cameras,
)


@pytest.mark.parametrize("model", sorted(PARAMS))
def test_k_distortion_and_colmap_round_trip(model: str) -> None:
    intr = Intrinsics(model, 640, 480, tuple(PARAMS[model]))
    k = intr.k_matrix
    assert k.shape == (3, 3) and (k[0, 2], k[1, 2]) == (319.5, 239.5) and k[2, 2] == 1.0
    assert intr.dist_coeffs.shape == (5,) and intr.dist_coeffs[4] == 0.0
    colmap = intr.colmap_params()
    assert colmap != list(intr.params)  # the principal point moves by half a pixel
    assert intrinsics_from_colmap(model, 640, 480, colmap) == intr


def test_a_model_no_stage_can_use_and_a_bad_pose_are_input_errors() -> None:
    with pytest.raises(InputError, match="not one of"):
        Intrinsics("FULL_OPENCV", 640, 480, (1.0,) * 12)
    with pytest.raises(InputError, match=r"cameras.json: poses\['a.jpg'\]"):
        parse_cameras({"intrinsics": PINHOLE, "poses": {"a.jpg": (np.eye(4) * 2).tolist()}})
    with pytest.raises(InputError, match="unknown keys"):
        parse_cameras({"images": {}})


def test_what_reconstruct_writes_reconstruct_and_compare_read_back(tmp_path: Path) -> None:
    """The output's cameras.json is the next stage's input: same intrinsics, same poses."""
    views = [
        CameraView("b.jpg", Intrinsics("OPENCV", 64, 48, tuple(PARAMS["OPENCV"])),
                   np.asarray(pose())),
        CameraView("a.jpg", Intrinsics("SIMPLE_PINHOLE", 64, 48, tuple(PARAMS["SIMPLE_PINHOLE"])),
                   np.asarray(pose(1.0, 0.5, (0.0, 0.0, 2.0)))),
    ]  # fmt: skip
    path = tmp_path / "cameras.json"
    write_cameras(path, views)
    assert set(json.loads(path.read_text())) == {"intrinsics_per_image", "poses"}
    spec = load_reconstruct_cameras(path)
    for view in views:
        assert spec.intrinsics_for(view.name) == view.intrinsics
        np.testing.assert_array_equal(spec.poses[view.name], view.env_from_cam)
    cams = load_cameras(path)
    assert [c.name for c in cams] == ["a.jpg", "b.jpg"]
    for cam, view in zip(cams, views[::-1], strict=True):
        np.testing.assert_array_equal(cam.k, view.intrinsics.k_matrix)
        np.testing.assert_allclose(cam.cam_from_env, invert_rigid(view.env_from_cam), atol=1e-12)
