"""Density clustering and hysteresis growth on point sets with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from tests.workers.pipeline.compare_scene import (
    BASE,
    CAMS,
    CLASSES,
    DIAMETERS,
    TWIN,
    Obj,
    capture,
    crate,
    run,
)
from workers.pipeline.compare import PRESETS
from workers.pipeline.compare.clusters import (
    _near_voxels,
    dbscan,
    grow_bases,
    grow_groups,
    prune_skirts,
    walls,
)
from workers.pipeline.compare.stage import compare_snapshots
from workers.pipeline.errors import ComparisonError


def _column(step: float = 0.01, height: float = 0.3) -> np.ndarray:
    z = np.arange(0.0, height, step)
    return np.column_stack([np.zeros_like(z), np.zeros_like(z), z])


def test_dbscan_separates_two_blobs_and_drops_specks() -> None:
    rng = np.random.default_rng(0)
    a = rng.normal(0, 0.01, (200, 3))
    b = rng.normal(0, 0.01, (100, 3)) + np.array([1.0, 0.0, 0.0])
    speck = rng.normal(0, 0.001, (5, 3)) + np.array([0.0, 1.0, 0.0])
    labels = dbscan(np.vstack([a, b, speck]), 0.02, 4, 30)
    assert set(labels[:200]) == {0} and set(labels[200:300]) == {1}
    assert set(labels[300:]) == {-1}


def test_growth_follows_low_points_up_to_the_path_limit() -> None:
    # points every 1 cm up a column; the cluster is z ≥ 5 cm; low points z ≥ 1 cm, plus a
    # low point 1 m away (not connected)
    pts = np.vstack([_column(), [[1.0, 0.0, 0.02]]])
    z = pts[:, 2]
    seeds = [np.flatnonzero((z >= 0.05 - 1e-9) & (pts[:, 0] == 0))]
    low = np.flatnonzero(z >= 0.01 - 1e-9)
    # 3.5 cm of path reaches z = 2 cm, not 1 cm
    (short,) = grow_groups(seeds, pts, low, radius=0.015, max_distance=0.035)
    assert z[short].min() == pytest.approx(0.02)
    # 10 cm reaches every connected low point, never the far one nor the z = 0 point (not low)
    (full,) = grow_groups(seeds, pts, low, radius=0.015, max_distance=0.1)
    assert z[full].min() == pytest.approx(0.01)
    assert len(pts) - 1 not in full and 0 not in full
    assert set(seeds[0]) <= set(full)
    # no reach, no growth
    (same,) = grow_groups(seeds, pts, low, radius=0.015, max_distance=0.0)
    np.testing.assert_array_equal(same, seeds[0])


def test_a_point_reached_by_two_clusters_joins_the_nearer() -> None:
    x = np.arange(10) * 0.01  # 10 points 1 cm apart on a line
    pts = np.column_stack([x, np.zeros_like(x), np.zeros_like(x)])
    left, right = np.array([0]), np.array([9])
    grown = grow_groups([left, right], pts, np.arange(10), radius=0.015, max_distance=1.0)
    assert grown[0].tolist() == [0, 1, 2, 3, 4]
    assert grown[1].tolist() == [5, 6, 7, 8, 9]


def test_growth_rejects_a_bad_radius() -> None:
    with pytest.raises(ComparisonError):
        grow_groups([np.array([0])], _column(), np.arange(5), radius=0.0, max_distance=0.1)


def test_base_growth_takes_the_columns_beneath_down_to_the_band() -> None:
    # a wall of points every 2 mm (x, z), 0–10 cm high, standing on a floor (z = 0) that
    # reaches 2 cm in front of it (y < 0); the group is the wall above 1 cm
    xs = np.arange(0.0, 0.05, 0.002)
    zs = np.arange(0.0, 0.1, 0.002)
    wall = np.array([[x, 0.0, z] for x in xs for z in zs])
    floor = np.array([[x, -y, 0.0] for x in xs for y in np.arange(0.002, 0.02, 0.002)])
    pts = np.vstack([wall, floor])
    group = np.flatnonzero((pts[:, 1] == 0.0) & (pts[:, 2] >= 0.01 - 1e-9))
    (grown,) = grow_bases([group], pts, radius_xy=0.001, band_m=0.007)
    added = np.setdiff1d(grown, group)
    # the wall's points 4–8 mm high join (within 7 mm of the group's lowest, 1 cm); lower
    # wall points and the floor in front do not
    assert set(group) <= set(grown)
    assert np.all(pts[added, 1] == 0.0)
    np.testing.assert_allclose(np.unique(pts[added, 2]), [0.004, 0.006, 0.008], atol=1e-9)
    # a band reaching the floor takes the wall down to it, never the floor beside the wall
    (deep,) = grow_bases([group], pts, radius_xy=0.001, band_m=0.02)
    assert np.all(pts[np.setdiff1d(deep, group), 1] == 0.0)
    assert pts[deep, 2].min() == pytest.approx(0.0)


def test_base_growth_gives_a_point_beneath_two_groups_to_the_nearer() -> None:
    pts = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.003], [0.0, 0.0, 0.01]])
    low, high = grow_bases([np.array([1]), np.array([2])], pts, radius_xy=0.001, band_m=0.02)
    assert low.tolist() == [0, 1] and high.tolist() == [2]
    with pytest.raises(ComparisonError):
        grow_bases([np.array([1])], pts, radius_xy=0.001, band_m=0.0)


def _wall_with_fillet() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A wall (x 0–5 cm, y = 0, z 0–10 cm, every 2 mm) on a floor (z = 0) that reaches 2 cm
    in front of it, and the smear stereo leaves at its foot: a fillet sloping out from the
    wall (y = −2 … −12 mm, z = 12 … 2 mm, 1 mm down per mm out). Returns (points, the group:
    the wall above 1 cm and the fillet, fillet indices)."""
    xs = np.arange(0.0, 0.05, 0.002)
    wall = [[x, 0.0, z] for x in xs for z in np.arange(0.0, 0.1, 0.002)]
    floor = [[x, -y, 0.0] for x in xs for y in np.arange(0.002, 0.02, 0.002)]
    fillet = [[x, -d, 0.014 - d] for x in xs for d in np.arange(0.002, 0.0121, 0.002)]
    pts = np.array(wall + floor + fillet)
    is_fillet = np.arange(len(pts)) >= len(wall) + len(floor)
    group = np.flatnonzero(is_fillet | ((pts[:, 1] == 0.0) & (pts[:, 2] >= 0.01 - 1e-9)))
    return pts, group, np.flatnonzero(is_fillet)


def test_walls_are_the_points_with_their_group_above_them() -> None:
    pts, group, fillet = _wall_with_fillet()
    (wall,) = walls([group], pts, radius_xy=0.001, rise_m=0.03)
    assert set(wall) <= set(group) - set(fillet)  # the fillet has nothing above it
    on_wall = group[(pts[group, 1] == 0.0) & (pts[group, 2] <= 0.09)]
    assert set(on_wall) <= set(wall)
    assert not np.any(pts[wall, 2] > 0.097)  # nor has the wall's top row
    with pytest.raises(ComparisonError):
        walls([group], pts, radius_xy=0.03, rise_m=0.03)


def test_base_growth_beneath_walls_takes_no_floor_from_under_the_fillet() -> None:
    pts, group, _ = _wall_with_fillet()
    # beneath every point: the floor under the fillet joins (y < 0, z = 0)
    (everywhere,) = grow_bases([group], pts, radius_xy=0.001, band_m=0.02)
    added = np.setdiff1d(everywhere, group)
    assert np.any((pts[added, 1] < 0) & (pts[added, 2] == 0.0))
    # beneath the walls only: the wall down to the floor, nothing in front of it
    anchors = walls([group], pts, radius_xy=0.001, rise_m=0.03)
    (beneath,) = grow_bases([group], pts, radius_xy=0.001, band_m=0.02, anchors=anchors)
    added = np.setdiff1d(beneath, group)
    assert set(group) <= set(beneath)
    assert np.all(pts[added, 1] == 0.0)
    assert pts[beneath, 2].min() == pytest.approx(0.0)
    with pytest.raises(ComparisonError):
        grow_bases([group, group], pts, radius_xy=0.001, band_m=0.02, anchors=anchors)


def _post_with_skirt_and_foot() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A square post 4 × 4 cm, 10 cm high (walls sampled every 2 mm), whose walls above
    2 cm are the seeds; grown: its walls below 2 cm, a smeared ring of floor 2–10 mm
    outside it at z = 3 mm, and a foot 2 mm thick reaching 10 cm out in +x.
    Returns (points, seed indices, grown indices)."""
    s = np.arange(0.0, 0.04 + 1e-9, 0.002)
    zs = np.arange(0.0, 0.1, 0.002)
    walls = [
        [x, y, z]
        for z in zs
        for x, y in {(a, b) for a in s for b in (0.0, 0.04)}
        | {(a, b) for a in (0.0, 0.04) for b in s}
    ]
    ring = [
        [x, y, 0.003]
        for x in np.arange(-0.01, 0.05 + 1e-9, 0.002)
        for y in np.arange(-0.01, 0.05 + 1e-9, 0.002)
        if max(-x, x - 0.04, -y, y - 0.04) >= 0.002 and x < 0.04
    ]
    foot = [[x, y, 0.002] for x in np.arange(0.042, 0.14, 0.002) for y in s]
    pts = np.array(walls + ring + foot)
    n_walls = len(walls)
    seeds = np.flatnonzero((np.arange(len(pts)) < n_walls) & (pts[:, 2] >= 0.02))
    grown = np.arange(len(pts))
    return pts, seeds, grown


def test_skirt_pruning_drops_the_smeared_floor_ring_and_keeps_walls_and_foot() -> None:
    pts, seeds, grown = _post_with_skirt_and_foot()
    (kept,) = prune_skirts([grown], [seeds], pts, radius_xy=0.002, rise_m=0.03, width_m=0.02)
    dropped = np.setdiff1d(grown, kept)
    assert set(seeds) <= set(kept)
    walls = (pts[:, 0] >= 0) & (pts[:, 0] <= 0.04) & (pts[:, 1] >= 0) & (pts[:, 1] <= 0.04)
    assert np.all(walls[kept] | (pts[kept, 0] > 0.04))  # nothing of the ring outside x ≤ 4 cm
    assert not np.any(walls[dropped] & (pts[dropped, 2] > 0.003))  # the walls' feet stay
    # the foot: its first 2 cm go with the ring, its far end (and so its extent) stays
    foot = np.flatnonzero((pts[:, 0] > 0.041) & (pts[:, 2] == 0.002))
    x_kept = pts[np.intersect1d(foot, kept), 0]
    assert not np.any((x_kept > 0.043) & (x_kept < 0.059))
    assert np.all(np.isin(foot[pts[foot, 0] > 0.061], kept))


def test_skirt_pruning_leaves_ungrown_groups_and_rejects_bad_arguments() -> None:
    pts, seeds, _ = _post_with_skirt_and_foot()
    (same,) = prune_skirts([seeds], [seeds], pts, radius_xy=0.002, rise_m=0.03, width_m=0.02)
    assert same.tolist() == sorted(seeds.tolist())
    with pytest.raises(ComparisonError):
        prune_skirts([seeds], [seeds], pts, radius_xy=0.0, rise_m=0.03, width_m=0.02)
    with pytest.raises(ComparisonError):
        prune_skirts([seeds, seeds], [seeds], pts, radius_xy=0.002, rise_m=0.03, width_m=0.02)


# The growth tests need seeds that miss an object's low parts: a strict threshold above the
# lower (lod) one, as on reconstructed clouds (the unclipped mean + 1σ, which the changed
# box's own distances lift above it in these sparse, 8 mm scenes; the default's clipped one
# stays at the unchanged surface's level, below the lod of an 8 mm spacing), and the coarse
# seen check (2 cm + 2 px of the 256-px z-buffer), which sees no 3 cm foot go.
GROWN = PRESETS["default"].replace(
    threshold={"kind": "mean_std", "k": 1.0},
    seen_tolerance_m=0.02,
    seen_tolerance_px=2.0,
    seen_zbuffer_max_side=None,
)


def test_growth_gives_back_the_base_of_an_added_box() -> None:
    before = capture(BASE, CAMS, seed=1)
    new = crate(0.6, 0.8)
    strict = GROWN.replace(grow_threshold=None)
    found = {}
    for name, options in {"strict": strict, "grown": GROWN}.items():
        res = run(before, [*BASE, new], options=options)
        (cluster,) = [c for c in res.clusters if c.object_name == "crate" and c.side == "added"]
        found[name] = cluster
        assert [(c.type, c.object_name) for c in res.changes] == [("added", "crate")]
    threshold = res.distances["added"].threshold
    low = res.distances["added"].grow_threshold
    assert low is not None and 0 < low < threshold
    # strict: nothing of the crate below the threshold (its base is near the old floor)
    assert found["strict"].bbox_min[2] > threshold - 0.01
    # grown: the base down to about the lower threshold, and more points
    assert found["grown"].bbox_min[2] < found["strict"].bbox_min[2] - 0.01
    assert found["grown"].n_points > found["strict"].n_points
    iou = {k: c.mean_iou["crate"] for k, c in found.items()}
    assert iou["grown"] > iou["strict"]


def test_the_stage_prunes_a_smeared_ring_of_floor_around_an_added_box() -> None:
    # stereo smears depth across an object's silhouette at its foot: here a ring of points
    # 3–15 mm outside the new crate's footprint, floating between the lower and the strict
    # threshold, which hysteresis growth takes in and skirt pruning must drop again
    before = capture(BASE, CAMS, seed=1)
    new = crate(0.6, 0.8)
    probe = run(before, [*BASE, new], options=GROWN).distances["added"]
    assert probe.grow_threshold is not None
    height = 0.5 * (probe.grow_threshold + probe.threshold)
    rng = np.random.default_rng(5)
    ring = rng.uniform(
        [0.6 - 0.215, 0.8 - 0.165, height], [0.6 + 0.215, 0.8 + 0.165, height], (1500, 3)
    )
    outside = np.maximum(np.abs(ring[:, 0] - 0.6) - 0.2, np.abs(ring[:, 1] - 0.8) - 0.15)
    ring = ring[outside >= 0.003]
    after = capture([*BASE, new], CAMS, seed=2, extra=ring)
    width = {}
    for name, options in {
        "pruned": GROWN,
        "kept": GROWN.replace(skirt_width_factor=0.0),
    }.items():
        res = compare_snapshots(before, after, TWIN, CLASSES, DIAMETERS, options)
        (cluster,) = [c for c in res.clusters if c.object_name == "crate" and c.side == "added"]
        width[name] = cluster.bbox_max[0] - cluster.bbox_min[0]
        assert cluster.bbox_min[2] < probe.threshold - 0.01  # the crate's own base stays
    assert width["kept"] > 0.4 + 0.02  # the ring widened it
    # what stays of it lies within a column radius of the walls (0.75 × the ~8 mm spacing)
    assert width["pruned"] < 0.4 + 2 * 0.0075 < width["kept"] - 0.01


def test_growth_gives_back_the_base_of_a_removed_box() -> None:
    # the base of a removed box lies within the depth tolerance of the floor the new
    # cameras see behind it, so "not seen ≠ removed" never passes it; growth must
    before = capture(BASE, CAMS, seed=1)
    strict = GROWN.replace(grow_threshold=None)
    found = {}
    for name, options in {"strict": strict, "grown": GROWN}.items():
        res = run(before, [BASE[1]], options=options)
        assert [(c.type, c.object_name) for c in res.changes] == [("removed", "crate")]
        found[name] = res.changes[0].cluster
    threshold = res.distances["removed"].threshold
    assert found["strict"].bbox_min[2] > threshold - 0.01
    assert found["grown"].bbox_min[2] < 0.01  # down to the floor (z = 0)
    assert found["grown"].mean_iou["crate"] > found["strict"].mean_iou["crate"]


def test_voxel_prefilter_keeps_every_point_within_reach() -> None:
    rng = np.random.default_rng(3)
    pts = rng.uniform(-1, 1, (5000, 3))
    seeds = rng.uniform(-0.5, 0.5, (40, 3))
    cell = 0.1
    near = np.linalg.norm(pts[:, None, :] - seeds[None, :, :], axis=2).min(axis=1) <= cell
    mask = _near_voxels(pts, seeds, cell)
    assert np.all(mask[near])  # a superset of the points within reach
    assert mask.sum() < 0.5 * len(pts)  # and it prunes


def test_growth_reaches_a_low_foot_far_from_the_rest() -> None:
    # an L-shaped "cart": a 30 cm upright and a 45 cm foot 3 cm high; only the upright is
    # found at the strict threshold, and only a reach of object size brings the foot back
    ell = Obj(2, (0.0, -0.2), (((0.0, 0.0), (0.1, 0.1, 0.3)), ((0.275, 0.0), (0.45, 0.1, 0.03))))
    before = capture([*BASE, ell], CAMS, seed=1)
    short = GROWN.replace(grow_max_diameters=0.05)  # 4 cm of path
    for options in (short, GROWN.replace(grow_threshold=None)):
        res = run(before, BASE, options=options)
        assert [(c.type, c.object_name) for c in res.changes] == [("unidentified", None)]
    res = run(before, BASE, options=GROWN)
    assert [(c.type, c.object_name) for c in res.changes] == [("removed", "cart")]
    cluster = res.changes[0].cluster
    assert cluster.bbox_max[0] - cluster.bbox_min[0] > 0.45  # upright and foot
    assert cluster.n_seed_points is not None and cluster.n_points > cluster.n_seed_points
