"""Evidence beyond a cluster's own capture: a removal the after capture's detector still
sees is a hole, not a change; a removed cluster the detector names only in part takes the
class of the twin instance it lies on; the occurrence gate on box area."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from tests.workers.pipeline.compare_scene import (
    BASE,
    CAMS,
    CLASSES,
    DIAMETERS,
    TWIN,
    Counter,
    Obj,
    capture,
    detections,
    twin_of,
)
from workers.pipeline.compare import PRESETS, CaptureData, ClusterResult, compare_snapshots
from workers.pipeline.compare.evidence import name_at_removals, name_by_twin, occurrence_boxes
from workers.pipeline.errors import InputError


@pytest.fixture(scope="module")
def before() -> CaptureData:
    return capture(BASE, CAMS, seed=1)


def _hole_after() -> CaptureData:
    """The after capture lost the crate's surface (a reconstruction hole), but its images
    still show the crate: the detections are those of the full scene."""
    lost = capture(BASE[1:], CAMS, seed=2)
    return dataclasses.replace(lost, detections=detections(CAMS, BASE))


def _identified(res: object) -> list[tuple[str, str | None]]:
    return [(c.type, c.object_name) for c in res.changes if c.type != "unidentified"]  # type: ignore[attr-defined]


def test_a_removal_the_after_detector_still_sees_is_no_change(before: CaptureData) -> None:
    after = _hole_after()
    off = PRESETS["default"].replace(still_there_metric=None)
    on = PRESETS["default"].replace(still_there_metric=0.3)
    res_off = compare_snapshots(before, after, TWIN, CLASSES, DIAMETERS, off, new_id=Counter())
    res_on = compare_snapshots(before, after, TWIN, CLASSES, DIAMETERS, on, new_id=Counter())
    assert _identified(res_off) == [("removed", "crate")]
    assert _identified(res_on) == []
    # the cluster stays in the table, named
    assert [c.object_name for c in res_on.clusters if c.side == "removed"] == ["crate"]


def test_a_real_removal_is_kept_with_the_check_on(before: CaptureData) -> None:
    after = capture(BASE[1:], CAMS, seed=2)
    on = PRESETS["default"].replace(still_there_metric=0.3)
    res = compare_snapshots(before, after, TWIN, CLASSES, DIAMETERS, on, new_id=Counter())
    assert _identified(res) == [("removed", "crate")]


def _cluster(
    side: str, centroid: tuple[float, float, float], metrics: dict[str, float]
) -> ClusterResult:
    pts = np.asarray(centroid, dtype=np.float64)[None, :] + np.zeros((5, 3))
    return ClusterResult(
        id=1,
        side=side,  # type: ignore[arg-type]
        indices=np.arange(5),
        points_env=pts,
        boxes={},
        occurrences=10,
        overlaps={k: 10 for k in metrics},
        mean_iou=dict(metrics),
        metrics=dict(metrics),
        object_name=None,
    )


def test_name_by_twin_needs_the_instance_and_the_metric() -> None:
    options = PRESETS["default"].replace(twin_identify_threshold=0.3)
    crate_at = tuple(TWIN[0].centroid.tolist())
    on_crate = _cluster("removed", crate_at, {"crate": 0.42, "bin": 0.0, "cart": 0.0})
    weak = _cluster("removed", crate_at, {"crate": 0.2, "bin": 0.0, "cart": 0.0})
    elsewhere = _cluster("removed", (1.8, 1.8, 0.1), {"crate": 0.42, "bin": 0.0, "cart": 0.0})
    added = _cluster("added", crate_at, {"crate": 0.42, "bin": 0.0, "cart": 0.0})
    named = name_by_twin([on_crate, weak, elsewhere, added], TWIN, DIAMETERS, options)
    assert [c.object_name for c in named] == ["crate", None, None, None]
    # off: nothing named
    off = PRESETS["default"].replace(twin_identify_threshold=None)
    assert [c.object_name for c in name_by_twin([on_crate], TWIN, DIAMETERS, off)] == [None]
    # the class scored must be the instance's: a bin metric on the crate's place is not it
    other = _cluster("removed", crate_at, {"crate": 0.0, "bin": 0.45, "cart": 0.0})
    assert name_by_twin([other], TWIN, DIAMETERS, options)[0].object_name is None


def test_occurrences_need_a_box_of_the_smallest_area(before: CaptureData) -> None:
    crate_pts = before.points_env[before.points_env[:, 2] > 0.05]
    crate_pts = crate_pts[np.linalg.norm(crate_pts[:, :2] - [-0.8, 0.5], axis=1) < 0.4]
    every = occurrence_boxes(crate_pts, before, None, PRESETS["default"])
    assert len(every) == len(CAMS)
    areas = sorted(float((b[2] - b[0]) * (b[3] - b[1])) for b in every.values())
    gate = 0.5 * (areas[0] + areas[-1])
    gated = occurrence_boxes(
        crate_pts, before, None, PRESETS["default"].replace(min_box_area_px=gate)
    )
    assert 0 < len(gated) < len(every)
    assert all((b[2] - b[0]) * (b[3] - b[1]) >= gate for b in gated.values())


@pytest.mark.parametrize(
    ("name", "value"),
    [
        ("min_box_area_px", -1.0),
        ("seen_tolerance_m", -0.01),
        ("twin_identify_threshold", 0.0),
        ("still_there_metric", 1.5),
    ],
)
def test_evidence_options_are_checked(name: str, value: float) -> None:
    with pytest.raises(InputError, match=name):
        PRESETS["default"].replace(**{name: value})


def test_a_flat_removal_is_seen_with_the_finer_seen_check() -> None:
    """A 2.5 cm high crate-class slab removed: the default seen check (2 cm + 2 px of a
    256-px z-buffer, about 6 cm at 3.6 m) sees none of it go; a 512-px seen z-buffer with
    3 mm + 1 px sees its top."""
    slab = Obj(0, (-0.6, 0.4), (((0.0, 0.0), (0.4, 0.3, 0.025)),))
    before = capture([slab, BASE[1]], CAMS, seed=1)
    after = capture([BASE[1]], CAMS, seed=2)
    twin = twin_of([slab, BASE[1]], ["slab-1", "bin-1"])
    coarse = PRESETS["default"].replace(
        seen_tolerance_m=0.02, seen_tolerance_px=2.0, seen_zbuffer_max_side=None
    )
    fine = coarse.replace(seen_tolerance_m=0.003, seen_tolerance_px=1.0, seen_zbuffer_max_side=512)
    res_coarse = compare_snapshots(
        before, after, twin, CLASSES, DIAMETERS, coarse, new_id=Counter()
    )
    res_fine = compare_snapshots(before, after, twin, CLASSES, DIAMETERS, fine, new_id=Counter())
    seen_coarse = res_coarse.stats["candidates_seen"]["removed"]
    seen_fine = res_fine.stats["candidates_seen"]["removed"]
    assert seen_fine > max(100, 5 * seen_coarse)
    assert ("removed", "crate") in _identified(res_fine)
    assert ("removed", "crate") not in _identified(res_coarse)


def test_an_added_cluster_at_a_removal_takes_its_best_other_class() -> None:
    options = PRESETS["default"].replace(twin_identify_threshold=0.3)
    removed = dataclasses.replace(
        _cluster("removed", (0.0, 0.0, 0.15), {"crate": 0.8, "bin": 0.0, "cart": 0.0}),
        id=10,
        object_name="crate",
    )
    best = _cluster("added", (0.05, 0.0, 0.2), {"crate": 0.1, "bin": 0.38, "cart": 0.0})
    second = _cluster("added", (-0.05, 0.0, 0.2), {"crate": 0.0, "bin": 0.33, "cart": 0.0})
    weak = _cluster("added", (0.0, 0.05, 0.2), {"crate": 0.0, "bin": 0.0, "cart": 0.2})
    far = _cluster("added", (1.5, 0.0, 0.2), {"crate": 0.0, "bin": 0.45, "cart": 0.0})
    named = name_at_removals([removed, best, second, weak, far], DIAMETERS, options)
    # one object per removal: the best-scoring fragment only; the far one is no swap
    assert [c.object_name for c in named] == ["crate", "bin", None, None, None]
    off = PRESETS["default"].replace(twin_identify_threshold=None)
    assert name_at_removals([removed, best], DIAMETERS, off)[1].object_name is None
