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
    bin_,
    capture,
    crate,
    detections,
    sample_box,
    twin_of,
)
from workers.pipeline.compare import PRESETS, CaptureData, ClusterResult, compare_snapshots
from workers.pipeline.compare.c2c import c2c_both_ways
from workers.pipeline.compare.candidates import on_other_surface
from workers.pipeline.compare.changes import classify_changes
from workers.pipeline.compare.evidence import (
    Captures,
    _other_capture_metric,
    join_split_objects,
    name_at_removals,
    name_by_twin,
    name_move_ends,
    occurrence_boxes,
    parts_of_standing_objects,
)
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


def _on(obj: Obj, side: str, metrics: dict[str, float], cid: int) -> ClusterResult:
    """A cluster of ``side`` made of points on ``obj``'s faces, with the given metrics."""
    c, size = obj.boxes()[0]
    pts = sample_box(np.random.default_rng(cid), c, size)
    return dataclasses.replace(
        _cluster(side, tuple(obj.centroid.tolist()), metrics),
        id=cid,
        indices=np.arange(len(pts)),
        points_env=pts,
    )


def test_a_move_end_is_named_where_the_class_was_not_before() -> None:
    """A crate moved from ``gone`` to ``new``; a second crate ``stays``. The removal is
    identified, the new place only scores 0.35: it is named crate. The unchanged crate's
    cluster scores higher, but the before capture's detector boxes a crate there: no end."""
    gone, new, stays, bin_at = crate(-0.8, 0.5), crate(0.6, 0.9), crate(0.2, -0.9), bin_(-0.6, -0.6)
    before = capture([gone, stays, bin_at], CAMS, seed=1)
    after = capture([new, stays, bin_at], CAMS, seed=2)
    options = PRESETS["default"].replace(twin_identify_threshold=0.3)
    removed = dataclasses.replace(
        _on(gone, "removed", {"crate": 0.8, "bin": 0.0, "cart": 0.0}, 1), object_name="crate"
    )
    on_stays = _on(stays, "added", {"crate": 0.5, "bin": 0.0, "cart": 0.0}, 2)
    at_new = _on(new, "added", {"crate": 0.35, "bin": 0.0, "cart": 0.0}, 3)
    weak = _on(bin_at, "added", {"crate": 0.2, "bin": 0.1, "cart": 0.0}, 4)
    clusters = [removed, on_stays, at_new, weak]

    def names(found: list[ClusterResult]) -> list[str | None]:
        return [c.object_name for c in found]

    named = name_move_ends(
        clusters, DIAMETERS, Captures(before, after, None, None, CLASSES), options
    )
    assert names(named) == ["crate", None, "crate", None]
    # a cluster that scores the class in the capture it is missing from was there then
    there = _other_capture_metric(
        on_stays, "crate", Captures(before, after, None, None, CLASSES), options
    )
    assert (
        there
        >= 0.3
        > _other_capture_metric(
            at_new, "crate", Captures(before, after, None, None, CLASSES), options
        )
    )
    # a class that already has an identified end on the other side names nothing more
    both = [removed, on_stays, dataclasses.replace(at_new, object_name="crate"), weak]
    assert names(
        name_move_ends(both, DIAMETERS, Captures(before, after, None, None, CLASSES), options)
    ) == names(both)
    # a piece of another standing crate is no other end
    both = Captures(before, after, None, None, CLASSES)
    assert names(name_move_ends(clusters, DIAMETERS, both, options, pieces={3}))[2] is None
    # the end's own place (the floor a removed crate covered) is no other end
    under = dataclasses.replace(at_new, points_env=removed.points_env * [1, 1, 0])
    assert names(
        name_move_ends(
            [removed, under], DIAMETERS, Captures(before, after, None, None, CLASSES), options
        )
    ) == [
        "crate",
        None,
    ]
    # too far for a move, or the rule off: nothing named
    near = options.replace(moved_max_distance=0.5)
    assert (
        names(
            name_move_ends(clusters, DIAMETERS, Captures(before, after, None, None, CLASSES), near)
        )[2]
        is None
    )
    off = options.replace(twin_identify_threshold=None)
    assert names(
        name_move_ends(clusters, DIAMETERS, Captures(before, after, None, None, CLASSES), off)
    ) == names(clusters)
    # the same from the other end: an identified addition names the removal that scores
    added = dataclasses.replace(at_new, object_name="crate", metrics={"crate": 0.8})
    loose_removal = dataclasses.replace(removed, object_name=None, metrics={"crate": 0.4})
    flipped = name_move_ends(
        [added, loose_removal], DIAMETERS, Captures(before, after, None, None, CLASSES), options
    )
    assert names(flipped) == ["crate", "crate"]


def test_a_hole_in_the_other_cloud_is_no_change() -> None:
    """Before: a floor with a 2 cm plate on it; after: the plate gone and the floor with a
    30 cm hole elsewhere. The before floor points over the hole are far from every after
    point, but on the after floor's plane: no change. The plate's points stand 2 cm above
    that plane: a change."""
    rng = np.random.default_rng(3)
    floor = np.c_[rng.uniform(-1, 1, (40_000, 2)), rng.normal(0, 0.001, 40_000)]
    hole = np.linalg.norm(floor[:, :2] - [0.5, 0.5], axis=1) < 0.15
    plate = np.c_[rng.uniform(-0.6, -0.4, (800, 2)), 0.02 + rng.normal(0, 0.001, 800)]
    before_pts = np.concatenate([floor, plate])
    after_pts = floor[~hole]
    c2c = c2c_both_ways(before_pts, after_pts)
    in_hole = np.flatnonzero(np.r_[hole, np.zeros(len(plate), dtype=bool)])
    on_plate = np.arange(len(floor), len(before_pts))

    def removed(cid: int, idx: np.ndarray) -> ClusterResult:
        return dataclasses.replace(
            _cluster("removed", (0.0, 0.0, 0.0), {"crate": 0.0}),
            id=cid,
            indices=idx,
            points_env=before_pts[idx],
        )

    clusters = [removed(1, in_hole), removed(2, on_plate)]
    threshold = {"added": 0.005, "removed": 0.005}
    assert float(np.median(c2c.removed[in_hole])) > 0.04  # far from every after point
    assert on_other_surface(clusters, c2c, threshold, PRESETS["default"]) == {1}
    off = PRESETS["default"].replace(check_seen_removed=False)
    assert on_other_surface(clusters, c2c, threshold, off) == set()


def test_a_piece_of_an_object_standing_in_both_captures_is_no_change() -> None:
    """A crate stands in both captures (a piece of it reconstructed differently); another
    is taken away. Only pieces of the first are inside crate detections in both captures."""
    stays, gone = crate(-0.8, 0.5), crate(0.6, -0.6)
    before = capture([stays, gone], CAMS, seed=1)
    after = capture([stays], CAMS, seed=2)
    piece = _on(stays, "added", {"crate": 0.2, "bin": 0.0, "cart": 0.0}, 1)
    piece = dataclasses.replace(piece, points_env=piece.points_env[piece.points_env[:, 2] > 0.25])
    taken = _on(gone, "removed", {"crate": 0.2, "bin": 0.0, "cart": 0.0}, 2)
    named = dataclasses.replace(piece, id=3, object_name="crate")
    found = parts_of_standing_objects(
        [piece, taken, named], Captures(before, after, None, None, CLASSES), PRESETS["default"]
    )
    # named or not (a piece on a twin instance takes its class at 0.3): still a piece
    assert found == {1, 3}
    off = PRESETS["default"].replace(still_there_metric=None)
    assert (
        parts_of_standing_objects([piece], Captures(before, after, None, None, CLASSES), off)
        == set()
    )


def test_a_piece_takes_part_in_no_change() -> None:
    """A named piece of a standing crate (removed side) beside a named added crate: a move
    without the piece check, nothing with it; the piece stays out of swaps and leftovers."""
    piece = dataclasses.replace(
        _cluster("removed", (0.0, 0.0, 0.1), {"crate": 0.32, "bin": 0.0, "cart": 0.0}),
        id=7,
        object_name="crate",
    )
    added = dataclasses.replace(
        _cluster("added", (0.1, 0.0, 0.1), {"crate": 0.5, "bin": 0.0, "cart": 0.0}),
        id=8,
        object_name="crate",
    )
    options = PRESETS["default"]

    def types(not_changes: set[int]) -> list[tuple[str, str | None]]:
        found = classify_changes(
            [piece, added], [], DIAMETERS, options, Counter(), not_changes=not_changes
        )
        return [(c.type, c.object_name) for c in found]

    assert types(set()) == [("moved", "crate")]
    assert types({7}) == [("added", "crate")]
    assert types({7, 8}) == []


def test_parts_of_one_object_split_in_two_clusters_are_one_change() -> None:
    """A bin (0.25 × 0.25 × 0.5 m) added, its body and top found as two clusters both named
    bin: the better named takes the top's points and the top is a part, no change of its
    own; a second bin 1 m away, a crate's cluster and a part of a standing object stay."""
    options = PRESETS["default"]
    body = dataclasses.replace(
        _cluster("added", (0.0, 0.0, 0.15), {"bin": 0.7}), id=1, object_name="bin"
    )
    body = dataclasses.replace(
        body, points_env=body.points_env + [[0, 0, -0.1]] + np.eye(3)[[0, 1, 2, 0, 1]] * 0.1
    )
    top = dataclasses.replace(
        _cluster("added", (0.05, 0.0, 0.4), {"bin": 0.55}), id=2, object_name="bin"
    )
    far = dataclasses.replace(
        _cluster("added", (1.0, 0.0, 0.2), {"bin": 0.6}), id=3, object_name="bin"
    )
    crate = dataclasses.replace(
        _cluster("added", (0.0, 0.1, 0.15), {"crate": 0.8}), id=4, object_name="crate"
    )
    removed = dataclasses.replace(
        _cluster("removed", (0.0, 0.0, 0.3), {"bin": 0.9}), id=5, object_name="bin"
    )
    standing = dataclasses.replace(
        _cluster("added", (0.0, 0.0, 0.3), {"bin": 0.65}), id=6, object_name="bin"
    )
    clusters = [body, top, far, crate, removed, standing]
    joined, parts = join_split_objects(clusters, DIAMETERS, options, skip={6})
    assert parts == {2}
    assert joined[0].n_points == body.n_points + top.n_points
    assert joined[0].merged_from == body.merged_from + top.merged_from
    assert [c.n_points for c in joined[2:]] == [c.n_points for c in clusters[2:]]
    # the better named one takes the other whatever the order
    joined, parts = join_split_objects([top, body], DIAMETERS, options)
    assert parts == {2} and joined[0] is top and joined[1].n_points == 10
