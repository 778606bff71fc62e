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
from workers.pipeline.pose.verify import FINAL_TURN_REASON, RUNNER_UP_REASON


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
    """The options a job posted reach :func:`estimate_pose` for every posed change; so does
    a move's previous pose, and never a swap's (the replaced object's, another model)."""
    floor, cube = floor_and_cube()
    compare_options = options_from_json("thesis")
    after = CaptureData(points_env=np.vstack([floor, cube]))
    result = compare_snapshots(
        CaptureData(points_env=floor), after, [], ["box"], {"box": 0.17}, compare_options
    )
    assert result.changes
    # each kind's own previous pose (changes are posed on threads, in any order)
    earlier = {"added": None, "moved": np.eye(4), "swapped": np.eye(4)}
    added = dataclasses.replace(
        result,
        changes=tuple(
            dataclasses.replace(ch, type=kind, object_name="box", previous_env_from_object=pose)
            for ch in result.changes
            for kind, pose in earlier.items()
        ),
    )
    used: list[PoseOptions] = []
    previous: list[Any] = []

    def fake_estimate(*args: Any, options: PoseOptions, **kwargs: Any) -> Any:
        used.append(options)
        previous.append(kwargs["previous_env_from_object"])
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
    assert len(previous) == 3 * len(result.changes)
    assert sum(p is earlier["moved"] for p in previous) == len(result.changes)
    assert all(p is None or p is earlier["moved"] for p in previous)


def _photo_fits(
    monkeypatch: pytest.MonkeyPatch, costs: dict[float, float | None]
) -> list[np.ndarray]:
    """Near-tie poses (shifted along x by each key) whose photo fit costs the value (None:
    no photo shows all of it); :func:`posing._on_photo_edges` answers from the table."""

    def fake(model: Any, pose: np.ndarray, sight: Any, options: Any) -> Any:
        cost = costs[float(pose[0, 3])]
        if cost is None:
            return None
        turned = [f"turned {pose[0, 3]:.0f}"]
        return pose, {"cost_px": cost}, (FINAL_TURN_REASON,), turned

    monkeypatch.setattr(posing_module, "_on_photo_edges", fake)
    poses = []
    for x in costs:
        pose = np.eye(4)
        pose[0, 3] = x
        poses.append(pose)
    return poses


@pytest.mark.parametrize(
    ("costs", "settled_for"),
    [
        ({0.0: 0.2, 1.0: 0.5, 2.0: 1.0}, 0),  # every near-tie ≥ 2 × the chosen pose's cost
        ({0.0: 0.3, 1.0: 0.5, 2.0: 1.0}, None),  # one near-tie within 2 ×: not settled
        ({0.0: 0.8, 1.0: 0.25, 2.0: 0.9}, 1),  # the photos prefer a near-tie by 3 ×
        ({0.0: 0.2, 1.0: 1.0, 2.0: None}, None),  # a near-tie no photo shows: not settled
    ],
)
def test_the_photos_edges_settle_a_near_tie_only_by_twice_the_cost(
    monkeypatch: pytest.MonkeyPatch, costs: dict[float, float | None], settled_for: int | None
) -> None:
    chosen, *near_ties = _photo_fits(monkeypatch, costs)
    moved = posing_module._on_photo_edges(None, chosen, None, None)  # type: ignore[arg-type]
    quality: dict[str, Any] = {"runner_up_ratio": 0.97, "chosen_by": "score"}
    reasons = [f"{RUNNER_UP_REASON} 0.97 of the best (> 0.85)", f"{FINAL_TURN_REASON} 4°", "x"]
    options = POSE_PRESETS["default"]
    pose, left = posing_module._photo_step(
        None,
        moved,
        near_ties,
        None,
        options,
        quality,
        reasons,  # type: ignore[arg-type]
        False,
    )
    if settled_for is None:
        assert "settled_by_photo_edges" not in quality
        assert pose is chosen and left == [reasons[0], "x", "turned 0"]
        return
    # the winner's own photo turn is judged; a near-tie switched to keeps the pose step's
    # reasons, a confirmation of its last fit was about another pose
    kept = ["x"] if settled_for == 0 else [reasons[1], "x"]
    assert left == [*kept, f"turned {settled_for}"]
    assert quality["settled_by_photo_edges"]["switched"] == (settled_for != 0)
    expected = chosen if settled_for == 0 else near_ties[settled_for - 1]
    assert pose is expected
    if settled_for:
        assert quality["chosen_by"] == "photo_edges" and quality["runner_up_ratio"] is None


@pytest.mark.parametrize(
    ("righted", "down_costs", "switched_to"),
    [
        (True, (0.4, 0.5), 2),  # upside down 3 × better than every upright pose: its best
        (False, (0.4, 0.5), None),  # the scan did not prefer upside down: the tie stands
        (True, (0.7, 0.8), None),  # upside down within 2 × of upright: not settled
    ],
)
def test_the_photos_settle_the_way_up_of_a_pose_stood_upright_against_the_scan(
    monkeypatch: pytest.MonkeyPatch,
    righted: bool,
    down_costs: tuple[float, float],
    switched_to: int | None,
) -> None:
    # the chosen pose (upright, 1.2 px), an upright near-tie (1.5 px) and two upside-down
    # ones turned about x; the two upside-down ones tie with each other
    costs = {0.0: 1.2, 1.0: 1.5, 2.0: down_costs[0], 3.0: down_costs[1]}
    chosen, *near_ties = _photo_fits(monkeypatch, costs)
    for pose in near_ties[1:]:
        pose[:3, :3] = np.diag([1.0, -1.0, -1.0])
    model = SimpleNamespace(up_object=np.array([0.0, 0.0, 1.0]))
    moved = posing_module._on_photo_edges(model, chosen, None, None)  # type: ignore[arg-type]
    quality: dict[str, Any] = {"runner_up_ratio": 1.4, "chosen_by": "up"}
    reasons = [f"{RUNNER_UP_REASON} 1.40 of the best (> 0.85)", "x"]
    pose, left = posing_module._photo_step(
        model,  # type: ignore[arg-type]
        moved,
        near_ties,
        None,  # type: ignore[arg-type]
        POSE_PRESETS["default"],
        quality,
        reasons,
        righted,
    )
    if switched_to is None:
        assert "settled_by_photo_edges" not in quality
        assert pose is chosen and left == [*reasons, "turned 0"]
        return
    # the way up is settled, not the near-ties standing that way: still unverified
    assert pose is near_ties[switched_to - 1]
    assert left == [*reasons, f"turned {switched_to}"]
    tie = quality["settled_by_photo_edges"]
    assert tie == {"cost_px": 0.4, "best_rival_px": 1.2, "switched": True, "way_up_only": True}
    assert quality["chosen_by"] == "photo_edges"


def test_the_way_up_rule_settles_nothing_when_no_pose_stands_upright(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # every pose upside down: there is no upright pose for the photos to beat
    chosen, *near_ties = _photo_fits(monkeypatch, {0.0: 1.2, 1.0: 0.4, 2.0: 0.5})
    for pose in (chosen, *near_ties):
        pose[:3, :3] = np.diag([1.0, -1.0, -1.0])
    model = SimpleNamespace(up_object=np.array([0.0, 0.0, 1.0]))
    moved = posing_module._on_photo_edges(model, chosen, None, None)  # type: ignore[arg-type]
    tie = posing_module._photo_tiebreak(
        model,  # type: ignore[arg-type]
        moved,
        near_ties,
        None,  # type: ignore[arg-type]
        POSE_PRESETS["default"],
        True,
    )
    assert tie is None
