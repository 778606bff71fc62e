"""The pose step after a comparison (workers.pipeline.pose.posing)."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from workers.pipeline.compare.data import CaptureData
from workers.pipeline.compare.options import options_from_json
from workers.pipeline.compare.stage import compare_snapshots
from workers.pipeline.errors import RegistrationError
from workers.pipeline.pose import posing as posing_module
from workers.pipeline.pose.options import POSE_PRESETS, PoseOptions
from workers.pipeline.pose.posing import cameras_from_json, pose_changes


def test_cameras_from_json_inverts_env_from_cam_and_sorts_by_name() -> None:
    env_from_cam = np.eye(4)
    env_from_cam[:3, 3] = [1.0, 2.0, 3.0]
    view = {"K": [[500, 0, 320], [0, 500, 240], [0, 0, 1]], "width": 640, "height": 480}
    cams = cameras_from_json(
        {
            "b.png": {**view, "env_from_cam": env_from_cam.tolist()},
            "a.png": {**view, "env_from_cam": np.eye(4).tolist()},
        }
    )
    assert [c.name for c in cams] == ["a.png", "b.png"]
    np.testing.assert_allclose(cams[1].cam_from_env @ env_from_cam, np.eye(4), atol=1e-12)


def floor_and_cube() -> tuple[np.ndarray, np.ndarray]:
    """A floor (5 mm grid, 1 m square) and a 10 cm cube standing on it at (0.2, 0.2)."""
    g = np.arange(-0.5, 0.5, 0.005)
    x, y = np.meshgrid(g, g)
    floor = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    c = np.arange(0.0, 0.1, 0.005)
    cube = np.array(
        [[a, b, h] for a in c for b in c for h in c if min(a, b, h) == 0 or max(a, b, h) >= 0.095]
    )
    return floor, cube + np.array([0.2, 0.2, 0.0])


def test_unidentified_changes_get_a_centroid_and_no_model_is_loaded() -> None:
    # the floor before; the same floor and the cube standing on it after
    floor, cube = floor_and_cube()
    options = options_from_json("thesis")
    result = compare_snapshots(
        CaptureData(points_env=floor),
        CaptureData(points_env=np.vstack([floor, cube])),
        [],
        ["box"],
        {"box": 0.17},
        options,
    )

    def never(name: str) -> object:
        raise AssertionError(f"model {name} loaded for an unidentified change")

    records = pose_changes(result, CaptureData(points_env=floor), ["box"], {"box"}, never, options)  # type: ignore[arg-type]
    assert records and all(r["type"] == "unidentified" for r in records)
    assert all(r.get("pose") is None and not r.get("pose_quality") for r in records)
    centre = np.mean([r["centroid_env"] for r in records], axis=0)
    np.testing.assert_allclose(centre[:2], [0.25, 0.25], atol=0.03)


def test_pose_changes_estimates_with_the_posted_options(monkeypatch: pytest.MonkeyPatch) -> None:
    """The options a job posted reach :func:`estimate_pose` for every posed change."""
    floor, cube = floor_and_cube()
    compare_options = options_from_json("thesis")
    after = CaptureData(points_env=np.vstack([floor, cube]))
    result = compare_snapshots(
        CaptureData(points_env=floor), after, [], ["box"], {"box": 0.17}, compare_options
    )
    assert result.changes
    added = dataclasses.replace(
        result,
        changes=tuple(
            dataclasses.replace(ch, type="added", object_name="box") for ch in result.changes
        ),
    )
    used: list[PoseOptions] = []

    def fake_estimate(*args: Any, options: PoseOptions, **kwargs: Any) -> Any:
        used.append(options)
        raise RegistrationError("no candidate (test)")

    monkeypatch.setattr(posing_module, "estimate_pose", fake_estimate)
    records = pose_changes(
        added,
        after,
        ["box"],
        {"box"},
        lambda name: SimpleNamespace(name=name),  # type: ignore[arg-type,return-value]
        compare_options,
        {"preset": "thorough", "max_rounds": 1},
    )
    assert used and all(
        o == dataclasses.replace(POSE_PRESETS["thorough"], max_rounds=1) for o in used
    )
    assert all(r["pose"] is None and not r["pose_quality"]["verified"] for r in records)
