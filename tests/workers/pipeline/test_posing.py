"""The pose step after a comparison (workers.pipeline.posing)."""

from __future__ import annotations

import numpy as np

from workers.pipeline.compare.data import CaptureData
from workers.pipeline.compare.options import options_from_json
from workers.pipeline.compare.stage import compare_snapshots
from workers.pipeline.posing import cameras_from_json, pose_changes


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


def test_unidentified_changes_get_a_centroid_and_no_model_is_loaded() -> None:
    # a floor (5 mm grid) before; the same floor and a 10 cm cube standing on it after
    g = np.arange(-0.5, 0.5, 0.005)
    x, y = np.meshgrid(g, g)
    floor = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    c = np.arange(0.0, 0.1, 0.005)
    cube = np.array(
        [[a, b, h] for a in c for b in c for h in c if min(a, b, h) == 0 or max(a, b, h) >= 0.095]
    )
    cube = cube + np.array([0.2, 0.2, 0.0])
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
