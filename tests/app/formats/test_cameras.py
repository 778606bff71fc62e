"""cameras.json: the one reader and writer (app/formats/cameras.py)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from app.formats import FormatError
from app.formats.cameras import (
    CAMERA_MODELS,
    Camera,
    CamerasFile,
    check_rigid,
    from_reconstruction_images,
    is_reconstruction_images,
    load_cameras_file,
    read_cameras,
    write_cameras,
)

PINHOLE = {"model": "PINHOLE", "width": 640, "height": 480, "params": [500, 510, 319.5, 239.5]}
PARAMS = {
    "SIMPLE_PINHOLE": [500.0, 319.5, 239.5],
    "PINHOLE": [500.0, 510.0, 319.5, 239.5],
    "SIMPLE_RADIAL": [500.0, 319.5, 239.5, 0.01],
    "RADIAL": [500.0, 319.5, 239.5, 0.01, -0.002],
    "OPENCV": [500.0, 510.0, 319.5, 239.5, 0.01, -0.002, 0.0001, -0.0002],
}


def rotation(rx: float, rz: float) -> np.ndarray:
    cx, sx, cz, sz = math.cos(rx), math.sin(rx), math.cos(rz), math.sin(rz)
    r_x = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    r_z = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return r_z @ r_x


def pose(rx: float = 0.3, rz: float = -1.2, t: tuple[float, ...] = (1.0, -2.0, 1.5)) -> list:
    m = np.eye(4)
    m[:3, :3] = rotation(rx, rz)
    m[:3, 3] = t
    return m.tolist()


def test_a_document_reads_back_equal_after_writing(tmp_path: Path) -> None:
    doc = {
        "intrinsics": PINHOLE,
        "intrinsics_per_image": {"b.jpg": {"model": "OPENCV", "width": 64, "height": 48,
                                           "params": PARAMS["OPENCV"]}},
        "poses": {"a.jpg": pose(), "b.jpg": np.eye(4).tolist()},
    }  # fmt: skip
    cams = read_cameras(doc, image_names={"a.jpg", "b.jpg"})
    assert cams.camera_for("a.jpg") == Camera("PINHOLE", 640, 480, (500.0, 510.0, 319.5, 239.5))
    assert cams.camera_for("b.jpg") is not None and cams.camera_for("b.jpg").model == "OPENCV"
    assert cams.camera_for("c.jpg") == cams.intrinsics
    np.testing.assert_array_equal(cams.poses["a.jpg"], pose())  # values kept exactly
    write_cameras(tmp_path / "cameras.json", cams)
    again = load_cameras_file(tmp_path / "cameras.json")
    assert again == cams
    assert json.loads((tmp_path / "cameras.json").read_text()) == cams.to_json()


@pytest.mark.parametrize("model", sorted(CAMERA_MODELS))
def test_every_model_a_stage_can_use_is_read_with_its_pinhole_and_distortion(model: str) -> None:
    cams = read_cameras({"intrinsics": {"model": model, "width": 640, "height": 480,
                                        "params": PARAMS[model]}})  # fmt: skip
    cam = cams.intrinsics
    assert cam is not None
    fx, fy, cx, cy = cam.pinhole
    assert (cx, cy) == (319.5, 239.5) and fx == 500.0
    assert fy == (510.0 if model in ("PINHOLE", "OPENCV") else 500.0)
    k1, k2, p1, p2, k3 = cam.distortion
    assert k3 == 0.0
    assert k1 == (0.0 if "PINHOLE" in model else 0.01)
    assert k2 == (-0.002 if model in ("RADIAL", "OPENCV") else 0.0)
    assert (p1, p2) == ((0.0001, -0.0002) if model == "OPENCV" else (0.0, 0.0))


@pytest.mark.parametrize(
    ("doc", "field", "problem"),
    [
        ([], "cameras.json", "expected a JSON object"),
        ({}, "cameras.json", "give 'intrinsics'"),
        ({"intrinsics": PINHOLE, "images": {}}, "cameras.json", "unknown keys ['images']"),
        ({"intrinsics": dict(PINHOLE, model="FULL_OPENCV")}, "cameras.json: intrinsics",
         "model 'FULL_OPENCV' is not one of"),
        ({"intrinsics": dict(PINHOLE, model="pinhole")}, "cameras.json: intrinsics", "model"),
        ({"intrinsics": dict(PINHOLE, params=[1, 2, 3])}, "cameras.json: intrinsics",
         "PINHOLE takes 4 params"),
        ({"intrinsics": dict(PINHOLE, params=[1, 2, "3", 4])}, "cameras.json: intrinsics",
         "finite numbers"),
        ({"intrinsics": dict(PINHOLE, params=[1, 2, float("nan"), 4])},
         "cameras.json: intrinsics", "finite numbers"),
        ({"intrinsics": dict(PINHOLE, width=0)}, "cameras.json: intrinsics", "width must be"),
        ({"intrinsics": dict(PINHOLE, height=True)}, "cameras.json: intrinsics", "height must"),
        ({"intrinsics_per_image": {}}, "cameras.json", "non-empty object"),
        ({"intrinsics_per_image": {"a.jpg": dict(PINHOLE, width=1.5)}},
         "cameras.json: intrinsics_per_image['a.jpg']", "width must be"),
        ({"intrinsics": PINHOLE, "poses": {"a.jpg": [[1, 0], [0, 1]]}},
         "cameras.json: poses['a.jpg']", "4×4 matrix"),
        ({"intrinsics": PINHOLE, "poses": {"a.jpg": np.diag([1.0, 1, -1, 1]).tolist()}},
         "cameras.json: poses['a.jpg']", "not a rotation"),
        ({"intrinsics": PINHOLE, "poses": {"a.jpg": np.diag([2.0, 1, 1, 1]).tolist()}},
         "cameras.json: poses['a.jpg']", "not a rotation"),
        ({"intrinsics": PINHOLE, "poses": {"a.jpg": (np.eye(4) + np.eye(4)[::-1] * 0.1)
                                           .tolist()}},
         "cameras.json: poses['a.jpg']", "last row"),
    ],
)  # fmt: skip
def test_a_bad_document_is_a_format_error_naming_the_field(
    doc: Any, field: str, problem: str
) -> None:
    with pytest.raises(FormatError) as err:
        read_cameras(doc)
    assert isinstance(err.value, ValueError)
    assert err.value.code == "InvalidCameras"
    assert err.value.field == field and problem in err.value.problem, err.value
    assert str(err.value) == f"{field}: {err.value.problem}"


def test_names_must_be_images_of_the_capture_when_given() -> None:
    doc = {"intrinsics": PINHOLE, "poses": {"a.jpg": pose(), "z.jpg": pose()}}
    assert set(read_cameras(doc).poses) == {"a.jpg", "z.jpg"}
    with pytest.raises(FormatError, match=r"not uploaded: \['z.jpg'\]"):
        read_cameras(doc, image_names={"a.jpg"})


def test_the_rigid_check_agrees_with_numpys_tolerances() -> None:
    """Oracle: the API's earlier numpy check (np.allclose on the last row, atol 1e-6, and on
    RᵀR = I, atol 1e-4, det ≥ 0), on rotations perturbed around both tolerances."""
    rng = np.random.default_rng(7)
    for _ in range(300):
        m = np.asarray(pose(*rng.uniform(-3, 3, 2), tuple(rng.uniform(-5, 5, 3))))
        m[:3, :3] += rng.normal(scale=10 ** rng.uniform(-7, -3), size=(3, 3))
        m[3, :3] += rng.normal(scale=10 ** rng.uniform(-8, -5), size=3)
        r = m[:3, :3]
        expected = (
            np.allclose(m[3], [0, 0, 0, 1], atol=1e-6)
            and np.allclose(r.T @ r, np.eye(3), atol=1e-4)
            and np.linalg.det(r) >= 0
        )
        try:
            check_rigid(m.tolist(), "m")
            accepted = True
        except FormatError:
            accepted = False
        assert accepted == expected


def test_unreadable_files_and_json_constants_are_format_errors(tmp_path: Path) -> None:
    with pytest.raises(FormatError, match="cannot read"):
        load_cameras_file(tmp_path / "missing.json")
    path = tmp_path / "cameras.json"
    path.write_text('{"intrinsics": {"model": "PINHOLE", "width": 4, "height": 4, '
                    '"params": [1, 1, NaN, 1]}}')  # fmt: skip
    with pytest.raises(FormatError, match="not JSON"):
        load_cameras_file(path)


def test_the_earlier_reconstruct_output_is_read_as_the_same_cameras() -> None:
    """Snapshots stored before reconstruct wrote the one format hold ``{"images": ...}``."""
    view = {"K": [[500, 0, 319.5], [0, 510, 239.5], [0, 0, 1]], "dist": [0] * 5, "width": 640,
            "height": 480, "intrinsics": PINHOLE, "env_from_cam": pose()}  # fmt: skip
    old = {"images": {"a.jpg": view}}
    assert is_reconstruction_images(old) and not is_reconstruction_images({"intrinsics": 1})
    cams = from_reconstruction_images(old)
    assert cams == read_cameras({"intrinsics_per_image": {"a.jpg": PINHOLE},
                                 "poses": {"a.jpg": pose()}})  # fmt: skip
    with pytest.raises(FormatError, match=r"images\['a.jpg'\].env_from_cam"):
        from_reconstruction_images({"images": {"a.jpg": dict(view, env_from_cam=[[1]])}})


def test_a_camera_refuses_a_model_no_stage_can_use() -> None:
    with pytest.raises(FormatError, match="not one of"):
        Camera("FISHEYE", 64, 48, (1.0, 2.0, 3.0, 4.0))
    assert CamerasFile().to_json() == {}
