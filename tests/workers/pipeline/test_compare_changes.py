"""Change detection on boxes with known offsets: added, removed, moved, swapped, merging of
split clusters, unidentified clusters, stable instance ids, the contract JSON."""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Sequence

import numpy as np
import pytest

from tests.workers.pipeline.compare_scene import (
    BASE,
    CAMS,
    CLASSES,
    DIAMETERS,
    TWIN,
    Counter,
    bin_,
    capture,
    cart,
    crate,
    run,
)
from workers.pipeline.compare import (
    PRESETS,
    CaptureData,
    ClusterResult,
    CompareOptions,
    CompareResult,
    TwinInstance,
    compare_snapshots,
)
from workers.pipeline.compare.changes import classify_changes
from workers.pipeline.errors import Cancelled, InputError
from workers.pipeline.geometry import make_rigid

# a cluster's centroid is the mean of its *changed* points (no floor-level rim, no
# bottom face), so it sits ~1–6 cm off the box centre; 8 cm is a safe bound at 8 mm spacing
CENTROID_TOL = 0.08


@pytest.fixture(scope="module")
def before() -> CaptureData:
    return capture(BASE, CAMS, seed=1)


def identified(res: CompareResult) -> list[tuple[str, str | None, str | None]]:
    return [(c.type, c.object_name, c.instance_id) for c in res.changes if c.type != "unidentified"]


def xy(c: ClusterResult) -> np.ndarray:
    return c.centroid[:2]


def test_add_one_box(before: CaptureData) -> None:
    res = run(before, [*BASE, crate(0.6, 0.8)])
    assert [(t, o) for t, o, _ in identified(res)] == [("added", "crate")]
    change = res.changes[0]
    assert np.linalg.norm(xy(change.cluster) - [0.6, 0.8]) < CENTROID_TOL
    assert change.instance_id not in {"crate-1", "bin-1"}
    assert change.env_from_object is None and change.previous_env_from_object is None
    assert change.cluster.side == "added" and len(change.cluster.indices) > 1000
    assert not [c for c in res.clusters if c.side == "removed"]


def test_remove_one_box(before: CaptureData) -> None:
    res = run(before, BASE[1:])
    assert identified(res) == [("removed", "crate", "crate-1")]
    change = res.changes[0]
    assert np.linalg.norm(xy(change.cluster) - [-0.8, 0.5]) < CENTROID_TOL
    np.testing.assert_array_equal(change.previous_env_from_object, TWIN[0].env_from_object)
    # the floor revealed under the crate is new geometry that matches no detection:
    # reported as unidentified, not dropped and not an object
    others = [c for c in res.changes if c.type == "unidentified"]
    assert all(c.cluster.side == "added" and c.cluster.bbox_max[2] < 0.03 for c in others)


def test_move_keeps_the_instance_id(before: CaptureData) -> None:
    res = run(before, [crate(0.2, -1.2), BASE[1]])
    assert identified(res) == [("moved", "crate", "crate-1")]
    moved = res.changes[0]
    assert moved.previous_cluster is not None
    assert np.linalg.norm(xy(moved.cluster) - [0.2, -1.2]) < CENTROID_TOL
    assert np.linalg.norm(xy(moved.previous_cluster) - [-0.8, 0.5]) < CENTROID_TOL
    np.testing.assert_array_equal(moved.previous_env_from_object, TWIN[0].env_from_object)


def test_swap_at_the_same_place(before: CaptureData) -> None:
    res = run(before, [bin_(-0.8, 0.5), BASE[1]])
    (swap,) = [c for c in res.changes if c.type == "swapped"]
    assert (swap.object_name, swap.replaced_object) == ("bin", "crate")
    assert swap.replaced_instance_id == "crate-1"
    assert swap.instance_id not in {"crate-1", "bin-1"}
    assert len(identified(res)) == 1


def test_split_clusters_are_merged(before: CaptureData) -> None:
    merged = run(before, [*BASE, cart(0.5, 0.9)])
    assert [(t, o) for t, o, _ in identified(merged)] == [("added", "cart")]
    assert len(merged.changes[0].cluster.merged_from) == 2
    assert np.linalg.norm(xy(merged.changes[0].cluster) - [0.5, 0.9]) < CENTROID_TOL
    # without merging: two halves, each too small for the detection box → unidentified,
    # and reported (not dropped)
    split = run(
        before, [*BASE, cart(0.5, 0.9)], options=PRESETS["default"].replace(merge_clusters=False)
    )
    assert identified(split) == []
    halves = [c for c in split.changes if c.type == "unidentified"]
    assert len(halves) == 2
    assert all(0 < c.cluster.metrics["cart"] < 0.5 for c in halves)


def test_merging_respects_the_class_size(before: CaptureData) -> None:
    small = {**DIAMETERS, "cart": 0.5}  # smaller than the two halves together
    after = capture([*BASE, cart(0.5, 0.9)], CAMS, seed=2)
    res = compare_snapshots(before, after, TWIN, CLASSES, small, new_id=Counter())
    assert all(len(c.merged_from) == 1 for c in res.clusters)


def test_instance_ids_are_stable_over_three_snapshots(before: CaptureData) -> None:
    # snapshot 1 → 2: a crate is added and gets a new id
    objs2 = [*BASE, crate(0.6, 0.8)]
    after2 = capture(objs2, CAMS, seed=2)
    res = compare_snapshots(before, after2, TWIN, CLASSES, DIAMETERS, new_id=Counter("a"))
    (added,) = [c for c in res.changes if c.type == "added"]
    pose = make_rigid(np.eye(3), [0.6, 0.8, 0.15])  # as the pose step would fill it
    twin2 = [*TWIN, TwinInstance(added.instance_id or "", "crate", pose, added.cluster.centroid)]
    # snapshot 2 → 3: that crate moves; the original crate and the bin stay put
    objs3 = [BASE[0], BASE[1], crate(0.9, -1.4)]
    after3 = capture(objs3, CAMS, seed=3)
    res3 = compare_snapshots(after2, after3, twin2, CLASSES, DIAMETERS, new_id=Counter("b"))
    assert identified(res3) == [("moved", "crate", added.instance_id)]
    np.testing.assert_array_equal(res3.changes[0].previous_env_from_object, pose)


def test_contract_json_and_progress(before: CaptureData) -> None:
    calls: list[tuple[str, float]] = []
    after = capture([crate(0.2, -1.2), BASE[1]], CAMS, seed=2)
    res = compare_snapshots(
        before, after, TWIN, CLASSES, DIAMETERS, progress=lambda s, f: calls.append((s, f))
    )
    doc = json.loads(json.dumps(res.to_json()))
    assert doc["options"]["threshold"] == {"kind": "mean_std", "k": 1.0, "clip": 6.0}
    for side in ("added", "removed"):
        assert {"mean", "std", "threshold"} <= set(doc["distances"][side])
    change = next(c for c in doc["changes"] if c["type"] == "moved")
    assert change["object"] == "crate" and change["instance_id"] == "crate-1"
    assert change["pose"] is None and len(change["previous_pose"]) == 4
    assert set(change["identification"]) >= {"metric", "iou", "overlaps", "occurrences"}
    assert change["identification"]["occurrences"] >= change["identification"]["overlaps"] > 0
    assert set(change["cluster"]) >= {"side", "n_points", "centroid", "bbox_min", "bbox_max"}
    table = doc["clusters"]
    assert all(set(row["metrics"]) == set(CLASSES) for row in table)
    assert [row["id"] for row in table] == list(range(1, len(table) + 1))
    assert calls[0] == ("compare.distances", 0.0) and calls[-1][1] == 1.0

    def cancel(stage: str, fraction: float) -> None:
        if fraction > 0.1:
            raise Cancelled("stop")

    with pytest.raises(Cancelled):
        compare_snapshots(before, after, TWIN, CLASSES, DIAMETERS, progress=cancel)
    with pytest.raises(InputError):
        compare_snapshots(before, after, TWIN, CLASSES, {"crate": -1.0})


def fake_cluster(cid: int, side: str, name: str | None, centre: Sequence[float]) -> ClusterResult:
    pts = np.asarray(centre, dtype=float) + np.random.default_rng(cid).normal(0, 0.05, (50, 3))
    return ClusterResult(
        id=cid,
        side=side,
        indices=np.arange(50),
        points_env=pts,
        boxes={},
        occurrences=3,  # type: ignore[arg-type]
        overlaps={},
        mean_iou={},
        metrics={},
        object_name=name,
    )


def test_pairing_rules_without_images() -> None:
    opts = CompareOptions(moved_max_distance=2.0, unidentified_min_points=1)
    diam = {"crate": 0.6, "bin": 0.6}
    clusters = [
        fake_cluster(1, "added", "crate", [3.0, 0, 0]),  # 3 m from the removed crate: not moved
        fake_cluster(2, "removed", "crate", [0.0, 0, 0]),
        fake_cluster(3, "added", "bin", [5.1, 0, 0]),  # 0.1 m from removed bin → moved
        fake_cluster(4, "removed", "bin", [5.0, 0, 0]),
        fake_cluster(5, "removed", "crate", [9.0, 0, 0]),  # swap partner 0.2 m away
        fake_cluster(6, "added", "bin", [9.2, 0, 0]),
        fake_cluster(7, "added", None, [20.0, 0, 0]),
    ]
    twin = [
        TwinInstance("c-a", "crate", make_rigid(np.eye(3), [0.05, 0, 0])),
        TwinInstance("b-a", "bin", make_rigid(np.eye(3), [5.0, 0, 0])),
        TwinInstance("c-far", "crate", make_rigid(np.eye(3), [9.0, 3.0, 0])),  # too far
    ]
    changes = classify_changes(clusters, twin, diam, opts, Counter())
    got = sorted((c.type, c.object_name, c.instance_id, c.cluster.id) for c in changes)
    assert got == [
        ("added", "crate", "id-6", 1),
        ("moved", "bin", "b-a", 3),
        ("removed", "crate", "c-a", 2),
        ("swapped", "bin", "id-3", 6),
        ("unidentified", None, None, 7),
    ]
    swap = next(c for c in changes if c.type == "swapped")
    assert swap.replaced_object == "crate" and swap.replaced_instance_id is None
    # a speck below unidentified_min_points, or one the old capture never saw as empty,
    # is not a change
    small = CompareOptions(moved_max_distance=2.0, unidentified_min_points=10**6)
    assert all(
        c.type != "unidentified" for c in classify_changes(clusters, twin, diam, small, Counter())
    )
    quiet = classify_changes(clusters, twin, diam, opts, Counter(), not_changes={7})
    assert all(c.type != "unidentified" for c in quiet)
    # a grown cluster counts only its points found at the strict threshold
    grown = dataclasses.replace(clusters[6], n_seed_points=5)
    ten = CompareOptions(moved_max_distance=2.0, unidentified_min_points=10)
    assert grown.n_points == 50 and grown.n_evidence_points == 5
    assert [c.type for c in classify_changes([grown], [], diam, ten, Counter())] == []
    kept = dataclasses.replace(grown, n_seed_points=10)
    assert [c.type for c in classify_changes([kept], [], diam, ten, Counter())] == ["unidentified"]


@pytest.mark.parametrize("preset", ["lod", "thesis"])
def test_add_one_box_with_other_presets(before: CaptureData, preset: str) -> None:
    res = run(before, [*BASE, crate(0.6, 0.8)], options=PRESETS[preset])
    assert [(t, o) for t, o, _ in identified(res)] == [("added", "crate")]
    assert res.distances["added"].threshold > 0
    if preset == "lod":  # σ ≈ 1 mm, 7.5 mm spacing → LoD ≈ sqrt((1.96·1.3)² + 15²) ≈ 15 mm
        assert 0.012 < res.distances["added"].threshold < 0.02
