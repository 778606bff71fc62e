"""CPU multi-view stereo: consistency filtering, pair depth accuracy, alignment refinement."""

from __future__ import annotations

import numpy as np
import pytest

from tests.workers.pipeline.reconstruct_scene import (
    k_matrix,
    look_at,
    render,
    ring_poses,
    texture,
)
from workers.pipeline.geometry import make_rigid, transform_points
from workers.pipeline.reconstruct.align import refine_alignment
from workers.pipeline.reconstruct.errors import DenseReconstructionFailed
from workers.pipeline.reconstruct.mvs import (
    DenseView,
    Neighbours,
    VerifiedDepths,
    _far_partners,
    _far_seed_partners,
    _overlay_far,
    _rectify,
    _sgbm_windows,
    consistent_points,
    consistent_points_split,
    disparity_window,
    far_disparity_window,
    fit_window,
    nearer_window,
    pair_depths,
    with_far_confirming_neighbours,
)
from workers.pipeline.reconstruct.options import ReconstructOptions


def _views(n: int = 8) -> list[DenseView]:
    tex = texture(0.12)
    return [
        DenseView(f"v{i}", render(tex, pose), k_matrix(), pose)
        for i, pose in enumerate(ring_poses(n))
    ]


def _true_depth(view: DenseView, half_m: float = 0.45) -> np.ndarray:
    """Exact depth of the textured floor (z = 0, |x|, |y| < ``half_m``) per pixel, else 0."""
    h, w = view.image.shape[:2]
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    k = view.k_matrix
    rays = np.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], np.ones_like(u, float)], -1)
    rot, c = view.env_from_cam[:3, :3], view.env_from_cam[:3, 3]
    dz = rays @ rot[2]  # env z-component of each ray per unit camera depth
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = -c[2] / dz
        xy = c[:2] + depth[..., None] * (rays @ rot[:2].T)
    on_texture = (depth > 0) & (np.abs(xy) < half_m).all(axis=-1)
    return np.where(on_texture, depth, 0.0).astype(np.float32)


def test_consistency_filter_removes_injected_outliers() -> None:
    """True depth maps for 8 views with 10 % of one view's pixels corrupted by ±10-40 %
    depth errors: fewer than 0.5 % of the corrupted pixels survive (they disagree with every
    neighbour), while ≥ 95 % of the true points are kept."""
    views = _views(8)
    depths = [_true_depth(v) for v in views]
    rng = np.random.default_rng(0)
    bad = (rng.random(depths[0].shape) < 0.10) & (depths[0] > 0)
    factor = rng.uniform(0.1, 0.4, size=bad.sum()) * rng.choice([-1, 1], size=bad.sum())
    depths[0][bad] *= (1 + factor).astype(np.float32)
    n = len(views)
    nbrs = Neighbours(
        stereo=tuple(() for _ in range(n)),
        consistency=tuple(tuple(j for j in range(n) if j != i) for i in range(n)),
    )
    opts = ReconstructOptions(point_stride=1, consistency_min_views=2)
    kept, _ = consistent_points(views, depths, nbrs, opts)
    z_err = np.abs(kept[:, 2])
    assert np.mean(z_err > 0.01) < 0.005 * bad.sum() / len(kept) + 1e-3
    assert np.median(z_err) < 1e-4
    total_true = sum(int((d > 0).sum()) for d in depths) - int(bad.sum())
    assert len(kept) >= 0.95 * total_true * 0.95  # some border pixels fall outside neighbours


@pytest.mark.slow
def test_far_pixels_use_the_far_consistency_tolerance() -> None:
    """View 0's depth is true, its 7 neighbours' 2 % too deep. With the floor (1-1.5 m) counted
    as far (far_min_depth_m = 0.5) and a 3 % far tolerance, view 0's pixels that its
    neighbours see are kept; with 1 % (or the floor counted as near, at the 1 % near
    tolerance) none is, and the stage reports an empty result."""
    views = _views(8)
    depths = [
        (_true_depth(v) * (1.0 if i == 0 else 1.02)).astype(np.float32) for i, v in enumerate(views)
    ]
    nbrs = Neighbours(
        stereo=tuple(() for _ in views),
        consistency=(tuple(range(1, 8)), *(() for _ in range(7))),
    )
    far = ReconstructOptions(point_stride=1, far_min_depth_m=0.5, far_consistency_rel_tol=0.03)
    kept, _ = consistent_points(views, depths, nbrs, far)
    assert len(kept) > 0.9 * (depths[0] > 0).sum()
    for opts in (
        ReconstructOptions(point_stride=1, far_min_depth_m=0.5, far_consistency_rel_tol=0.01),
        ReconstructOptions(point_stride=1, far_min_depth_m=5.0, far_consistency_rel_tol=0.03),
    ):
        with pytest.raises(DenseReconstructionFailed):
            consistent_points(views, depths, nbrs, opts)


def test_a_refuted_far_depth_falls_back_to_its_verified_one_checked_by_its_views() -> None:
    """View 0 holds a far depth 2 % too deep (within the 3 % far tolerance of the true floor,
    as a far SGBM depth that agreed with a verified plane depth), the true depth as its
    fallback, one consistency neighbour that sees nothing, and view 2 (its depth also 2 %
    too deep) as the view its plane depths were checked against. The measured depth has no
    support and is dropped; the fallback depth is kept on view 2's agreement, flagged as
    verified, at its own depth (not averaged with view 2's: median |z| < 0.1 mm, not 1 %).
    Without the checking views, or without the fallback, nothing survives."""
    views = _views(8)
    truth = [_true_depth(v) for v in views]
    depths = [(t * 1.02).astype(np.float32) for t in truth]
    depths[1] = np.zeros_like(depths[1])
    n = len(views)
    nbrs = Neighbours(
        stereo=tuple(() for _ in range(n)), consistency=((1,), *(() for _ in range(n - 1)))
    )
    opts = ReconstructOptions(
        point_stride=1, far_min_depth_m=0.5, far_consistency_rel_tol=0.03, planar_far_row_stride=1
    )
    verified = [np.zeros(d.shape, np.bool_) for d in depths]
    fallback = [truth[0], *(np.zeros_like(d) for d in depths[1:])]
    checked_by = [(2,), *(() for _ in range(n - 1))]
    kept = consistent_points_split(
        views, depths, nbrs, opts, verified=VerifiedDepths(verified, checked_by, fallback)
    )
    pts, src, own = kept.points_env, kept.verified, kept.depth_m
    seen_by_2 = int((truth[0] > 0).sum())
    assert 0.3 * seen_by_2 < len(pts) <= seen_by_2
    assert src.all() and np.median(np.abs(pts[:, 2])) < 1e-4
    assert np.isin(own, truth[0][truth[0] > 0]).all()  # the fallback depths, not 2 % deeper
    for only in (
        VerifiedDepths(verified, fallback=fallback),
        VerifiedDepths(verified, checked_by=checked_by),
    ):
        with pytest.raises(DenseReconstructionFailed):
            consistent_points_split(views, depths, nbrs, opts, verified=only)


def test_sgbm_pair_depths_are_millimetre_accurate_on_a_plane() -> None:
    """One rectified SGBM pair (about 30° apart at ~1.1 m) gives both views' depth: the median
    error over valid pixels is < 1 mm in each (HH4 SGBM; 3-way is biased by ~0.3 px on
    slanted surfaces; the partner's map is the disparity warped to it) and ≥ 60 % of the
    textured floor gets a depth in each."""
    views = _views(12)
    pts = np.random.default_rng(0).uniform([-0.4, -0.4, 0.0], [0.4, 0.4, 0.0], size=(300, 3))
    estimates = pair_depths(views[0], views[1], pts, ReconstructOptions())
    for view, est in zip(views[:2], estimates, strict=True):
        true = _true_depth(view)
        ok = (est > 0) & (true > 0)
        assert ok.sum() > 0.6 * (true > 0).sum()  # the rest is outside the partner view
        assert np.median(np.abs(est[ok] - true[ok])) < 0.001
        assert np.percentile(np.abs(est[ok] - true[ok]), 95) < 0.005


def _seen_by(view: DenseView, other: DenseView, depth: np.ndarray) -> np.ndarray:
    """Pixels of ``view`` with a true ``depth`` whose surface point projects inside ``other``."""
    h, w = depth.shape
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    k = view.k_matrix
    rays = np.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], np.ones_like(u, float)], -1)
    pts = transform_points(view.env_from_cam, (rays * depth[..., None]).reshape(-1, 3))
    cam = transform_points(other.cam_from_env, pts)
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = cam[:, :2] / cam[:, 2:] * np.diag(other.k_matrix)[:2] + other.k_matrix[:2, 2]
    inside = (cam[:, 2] > 0) & (uv >= 8).all(axis=1) & (uv[:, 0] < w - 8) & (uv[:, 1] < h - 8)
    return np.asarray((depth > 0) & inside.reshape(h, w))


def test_a_pair_gives_depth_up_to_the_image_edge_its_partner_sees() -> None:
    """Two views 10 cm apart sideways, looking down the floor: SGBM leaves the left image's
    first minDisparity + numDisparities columns (here 192) unmatched, though the far floor's
    matches lie in the right image from column ~60 on. Padded, the left view's columns
    64-192 get depth for ≥ 80 % of the floor both views see (unpadded: none), and each view
    for ≥ 80 % over the whole image (unpadded: 73 % and 69 %)."""
    tex = texture(0.12)
    views = [
        DenseView(f"v{i}", render(tex, pose), k_matrix(), pose)
        for i, pose in enumerate(
            look_at(np.array([x, -0.5, 0.45]), np.array([x, 0.15, 0.0])) for x in (-0.05, 0.05)
        )
    ]
    pts = np.random.default_rng(0).uniform([-0.4, -0.4, 0.0], [0.4, 0.4, 0.0], size=(300, 3))
    windows = _sgbm_windows(views[0], _rectify(*views), pts, ReconstructOptions(), False)
    assert windows == [(0, 192)]
    estimates = pair_depths(views[0], views[1], pts, ReconstructOptions())
    for view, other, est in zip(views, views[::-1], estimates, strict=True):
        both = _seen_by(view, other, _true_depth(view))
        assert (est[both] > 0).mean() > 0.8
    band = _seen_by(views[0], views[1], _true_depth(views[0]))[:, 64:192]
    assert (estimates[0][:, 64:192][band] > 0).mean() > 0.8


def test_disparity_window_reaches_far_and_keeps_most_points_when_over_budget() -> None:
    """Sparse disparities 100-200 px: the window ends above the nearest (p99 × 1.15 + 2) and
    reaches down to 0 px = infinity (a far wall with no sparse point is still searched).
    60 % of points at 100-150 px and 40 % at 500-600 px (span over the budget): the window
    holds the larger group."""
    rng = np.random.default_rng(0)
    start, num = disparity_window(rng.uniform(100, 200, 500), 256)
    assert start == 0 and 1.15 * 199 + 2 <= num <= 256  # from infinity (0 px) to the nearest
    start, num = disparity_window(
        np.concatenate([rng.uniform(100, 150, 600), rng.uniform(500, 600, 400)]), 256
    )
    assert num == 256 and start <= 100 and start + num >= 150


def test_nearer_window_covers_what_the_first_window_leaves_out_on_its_near_side() -> None:
    """60 % of the points at 100-150 px, 40 % at 500-600 px: the first window holds the far
    group; the second starts 16 px below its near end and spends the budget towards the near
    group. A few stray points (< 1 %) or a first window holding everything give none."""
    rng = np.random.default_rng(0)
    d = np.concatenate([rng.uniform(100, 150, 600), rng.uniform(500, 600, 400)])
    first = disparity_window(d, 256)
    start, num = nearer_window(d, first, 256)
    assert start == first[0] + first[1] - 16 and num == 256
    far = rng.uniform(100, 150, 1000)
    assert (
        nearer_window(np.concatenate([far, [600.0] * 5]), disparity_window(far, 256), 256) is None
    )
    assert nearer_window(far, disparity_window(far, 256), 256) is None


def _board_scene() -> tuple[list[DenseView], np.ndarray, list[np.ndarray]]:
    """Two views 10 cm apart looking straight down from 1 m at the floor (56 px of disparity)
    and a 20 cm textured board 0.4 m below them (140 px); 300 sparse floor points and 60 on
    the board; each view's true depth (H, W)."""
    floor_tex, board_tex = texture(0.12), texture(0.12, seed=1)
    board_z, half = 0.6, 0.1
    views, depths = [], []
    blank = np.zeros_like(render(floor_tex, np.eye(4)))
    for i, x in enumerate((-0.05, 0.05)):
        pose = look_at(np.array([x, 0.0, 1.0]), np.array([x, 0.001, 0.0]))
        lowered = pose.copy()
        lowered[2, 3] -= board_z  # the plane z = board_z seen as z = 0
        on_floor = _true_depth(DenseView("f", blank, k_matrix(), pose))
        at_board = _true_depth(DenseView("b", blank, k_matrix(), lowered), half_m=half)
        board = at_board > 0
        image = np.where(board[..., None], render(board_tex, lowered), render(floor_tex, pose))
        views.append(DenseView(f"v{i}", image, k_matrix(), pose))
        depths.append(np.where(board, at_board, on_floor))
    rng = np.random.default_rng(0)
    pts = np.concatenate(
        [
            rng.uniform([-0.4, -0.4, 0.0], [0.4, 0.4, 0.0], size=(300, 3)),
            rng.uniform([-half, -half, board_z], [half, half, board_z], size=(60, 3)),
        ]
    )
    return views, pts, depths


def test_a_near_board_outside_the_pairs_window_gets_depth_from_a_second_window() -> None:
    """With a 64 px budget the floor (56 px) and the board (140 px) do not fit one window: the
    first holds the floor and ends below the board (alone, it gave 23 % of the board's
    pixels, all about 9 cm wrong). With the second, ≥ 50 % of the board's pixels get a depth
    (one 256 px window: 53 %) and ≥ 70 % of the floor's (the first alone: 73 %), both with a
    median error < 1 mm: where the two runs disagree, the better-correlating match wins."""
    views, pts, depths = _board_scene()
    opts = ReconstructOptions(max_disparities=64)
    rect = _rectify(*views)
    windows = _sgbm_windows(views[0], rect, pts, opts, False)
    assert len(windows) == 2 and sum(windows[0]) < rect.f_px * rect.baseline_m / 0.4
    est = pair_depths(views[0], views[1], pts, opts)[0]
    true = depths[0]
    for region, share in ((true < 0.5, 0.5), (true > 0.9, 0.7)):  # board, floor
        ok = region & (true > 0) & (est > 0)
        assert ok.sum() > share * (region & (true > 0)).sum()
        assert np.median(np.abs(est[ok] - true[ok])) < 0.001


def test_fit_window_cuts_the_window_to_the_rectified_width() -> None:
    """A window reaching past the grid's width (a near surface at half scale) made OpenCV's
    SGBM ask for 2^64 bytes; it is cut in steps of 16, or dropped when nothing is left."""
    assert fit_window((40, 128), 640, 5) == (40, 128)  # fits: unchanged
    assert fit_window((200, 128), 320, 5) == (200, 112)  # 320 - 5 - 200 = 115 -> 112
    assert fit_window((300, 64), 320, 5) is None  # 15 disparities left
    assert fit_window((0, 256), 160, 5) == (0, 144)


def test_a_window_past_the_grid_width_gives_no_depth_instead_of_an_opencv_error() -> None:
    """A far-range pair whose window ends at 700 px on a 640 px grid (3-way SGBM, as the fast
    preset at half scale met it): before fit_window OpenCV failed asking for 2^64 bytes."""
    views = _views(12)
    pts = np.random.default_rng(0).uniform([-0.4, -0.4, 0.0], [0.4, 0.4, 0.0], size=(300, 3))
    rect = _rectify(views[0], views[1])
    near_px = 700  # far_disparity_window's near end: f·b / far_min_depth_m
    opts = ReconstructOptions(
        far_min_depth_m=rect.f_px * rect.baseline_m / near_px,
        far_max_disparities=64,
        sgbm_mode="3way",
    )
    estimates = pair_depths(views[0], views[1], pts, opts, far_range=True)
    for view, est in zip(views[:2], estimates, strict=True):
        assert est.shape == view.image.shape[:2]
        assert not est.any()  # 636-700 px: nothing left to search on a 640 px grid


def test_far_disparity_window_covers_from_the_minimum_depth_to_infinity_within_budget() -> None:
    """f·b = 520 px·m (650 px, 0.8 m): 3 m is 173.3 px, so 128 disparities cover 46-174 px
    (3-11 m); with f·b = 260 the window reaches 0 px = infinity."""
    start, num = far_disparity_window(520.0, 3.0, 128)
    assert (start, num) == (46, 128) and start + num >= 520 / 3.0
    assert far_disparity_window(260.0, 3.0, 128) == (0, 128)


def _ring_of_12() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centres (12, 3) and optical axes (12, 3) of 12 ring views, and (12, 12) shared sparse
    point counts of 100 between every two of them."""
    poses = ring_poses(12)
    centres = np.stack([p[:3, 3] for p in poses])
    axes = np.stack([p[:3, 2] for p in poses])
    return centres, axes, np.full((12, 12), 100.0, np.float32)


def test_far_partners_pair_every_view_once_with_a_wide_baseline() -> None:
    """12 views on a ring, 30° apart, looking down at the centre (axes 18° apart for
    neighbours, 34° two steps apart): with a 40° axis limit each view's far pair is with a
    view two steps away (the widest allowed baseline); every view is in exactly one far
    pair, so there are 6 pairs; with the option off there are none."""
    centres, axes, shared = _ring_of_12()
    far = _far_partners(centres, axes, shared, ReconstructOptions(far_max_axis_angle_deg=40.0))
    pairs = {(min(i, j), max(i, j)) for i, js in enumerate(far) for j in js}
    members = [v for pair in pairs for v in pair]
    assert sorted(members) == list(range(12))
    for i, j in pairs:
        assert np.degrees(np.arccos(np.clip(axes[i] @ axes[j], -1, 1))) <= 40.0
        assert (j - i) % 12 in (2, 10)
    no_far = ReconstructOptions(far_range=False)
    assert _far_partners(centres, axes, shared, no_far) == tuple(() for _ in range(12))


def test_far_seed_partners_give_the_views_without_a_far_pair_of_their_own_one() -> None:
    """The 12-view ring of the test above: the 6 views that are only the partner of an
    earlier view's far pair each get a plane-seed partner of their own (axes within 40°,
    not a pair already made), the other 6 none; none with the planar prior or far range
    off."""
    centres, axes, shared = _ring_of_12()
    opts = ReconstructOptions(far_max_axis_angle_deg=40.0)
    far = _far_partners(centres, axes, shared, opts)
    seed = _far_seed_partners(centres, axes, shared, far, opts)
    far_pairs = {(min(i, j), max(i, j)) for i, js in enumerate(far) for j in js}
    seed_pairs = {(min(i, j), max(i, j)) for i, js in enumerate(seed) for j in js}
    assert [len(s) for s in seed] == [0 if f else 1 for f in far] and sum(map(len, seed)) == 6
    assert not far_pairs & seed_pairs and len(seed_pairs) == 6
    for i, j in seed_pairs:
        assert np.degrees(np.arccos(np.clip(axes[i] @ axes[j], -1, 1))) <= 40.0
    for off in (ReconstructOptions(planar_prior=False), ReconstructOptions(far_range=False)):
        assert _far_seed_partners(centres, axes, shared, far, off) == tuple(() for _ in range(12))


def test_far_confirming_neighbours_are_the_views_whose_depths_agree() -> None:
    """View 0's one consistency neighbour has no depth; views 3 and 5 hold the true floor
    depth, view 6 one 10 % too deep, the rest none. With the floor counted as far, views 3
    and 5 are added to view 0's neighbours (not 6, beyond the 3 % tolerance), then view 0's
    pixels pass the check with two agreeing views; with one allowed, one of the two."""
    views = _views(8)
    truth = [_true_depth(v) for v in views]
    depths = [np.zeros_like(t) for t in truth]
    depths[0], depths[3], depths[5] = truth[0], truth[3], truth[5]
    depths[6] = (truth[6] * 1.1).astype(np.float32)
    nbrs = Neighbours(stereo=tuple(() for _ in views), consistency=((1,), *(() for _ in range(7))))
    opts = ReconstructOptions(point_stride=1, far_min_depth_m=0.5, far_consistency_rel_tol=0.03)
    wider = with_far_confirming_neighbours(views, depths, nbrs, opts)
    assert wider.consistency[0][0] == 1 and set(wider.consistency[0][1:]) == {3, 5}
    assert wider.stereo == nbrs.stereo
    with pytest.raises(DenseReconstructionFailed):
        consistent_points(views, depths, nbrs, opts)
    only_0 = Neighbours(nbrs.stereo, (wider.consistency[0], *(() for _ in range(7))))
    kept, _ = consistent_points(views, depths, only_0, opts)
    assert len(kept) > 0.2 * (truth[0] > 0).sum()
    assert np.median(np.abs(kept[:, 2])) < 5e-4 and np.abs(kept[:, 2]).max() < 0.01
    one = with_far_confirming_neighbours(
        views, depths, nbrs, ReconstructOptions(far_min_depth_m=0.5, consistency_views=1)
    )
    assert len(one.consistency[0]) == 2 and one.consistency[0][1] in (3, 5)


def test_far_overlay_keeps_near_occluders_and_fills_the_rest() -> None:
    """Far depth wins where the near pairs have none or see beyond far_min_depth_m; a near
    surface (1 m) is kept even where the far pair has a (spurious) depth."""
    near = np.array([[0.0, 1.0, 4.0, 4.0]], np.float32)
    far = np.array([[5.0, 6.0, 4.01, 0.0]], np.float32)
    out = _overlay_far(near, far, ReconstructOptions(far_min_depth_m=3.0))
    assert out.tolist() == [[5.0, 1.0, np.float32(4.01), 4.0]]


def test_far_range_pair_is_accurate_inside_its_window() -> None:
    """The plane pair of the SGBM test run as a far-range pair whose window starts at 0.8 m
    (the floor is 1-1.5 m away): it is as accurate as the near-range run, and restricting
    it to the rows where the near-range maps lack depth (here: none known) matches every
    row."""
    views = _views(12)
    pts = np.random.default_rng(0).uniform([-0.4, -0.4, 0.0], [0.4, 0.4, 0.0], size=(300, 3))
    opts = ReconstructOptions(far_min_depth_m=0.8, far_max_disparities=256)
    unknown = np.zeros(views[0].image.shape[:2], np.float32)
    estimates = pair_depths(views[0], views[1], pts, opts, True, (unknown, unknown))
    for view, est in zip(views[:2], estimates, strict=True):
        true = _true_depth(view)
        ok = (est > 0) & (true > 0)
        assert ok.sum() > 0.5 * (true > 0).sum()
        assert np.median(np.abs(est[ok] - true[ok])) < 0.001
        assert est[est > 0].min() >= 0.8 * 0.99


@pytest.mark.parametrize("opts", [ReconstructOptions(icp_voxel_m=0.01), ReconstructOptions()])
def test_alignment_refinement_ignores_a_changed_object(opts: ReconstructOptions) -> None:
    """Reference: floor + box A. New snapshot: floor + box B elsewhere, offset by 4 mm and
    0.3°. The Tukey ICP recovers the offset within 0.5 mm (the moved box does not pull it),
    with 1 cm voxels and with the defaults (8 mm voxels), and the same inputs give the same
    correction to the bit (Open3D's threads sum in any order)."""
    rng = np.random.default_rng(2)
    floor = np.column_stack([rng.uniform(-1, 1, (40000, 2)), np.zeros(40000)])
    wall = np.column_stack(
        [rng.uniform(-1, 1, 15000), np.full(15000, 1.0), rng.uniform(0, 1, 15000)]
    )
    wall2 = np.column_stack(
        [np.full(15000, -1.0), rng.uniform(-1, 1, 15000), rng.uniform(0, 1, 15000)]
    )

    def box(centre: list[float]) -> np.ndarray:
        p = rng.uniform(-0.1, 0.1, (6000, 3))
        axis = rng.integers(0, 3, 6000)
        p[np.arange(6000), axis] = np.sign(p[np.arange(6000), axis]) * 0.1
        return np.asarray(p + np.asarray(centre) + [0, 0, 0.1], np.float64)

    ref = np.concatenate([floor, wall, wall2, box([0.3, 0.2, 0.0])])
    new_true = np.concatenate([floor, wall, wall2, box([-0.4, -0.3, 0.0])])
    c, s = np.cos(np.radians(0.3)), np.sin(np.radians(0.3))
    new_from_env = make_rigid([[c, -s, 0], [s, c, 0], [0, 0, 1]], [0.003, -0.002, 0.002])
    new = transform_points(new_from_env, new_true)
    res = refine_alignment(new, ref, opts)
    assert res.applied
    probe = np.array([[0.5, 0.5, 0.2], [-0.5, 0.2, 0.5]])
    moved = transform_points(res.env_from_new @ new_from_env, probe)
    assert np.abs(moved - probe).max() < 5e-4
    assert res.translation_m > 0.002
    assert res.residual_m < res.residual_before_m
    for _ in range(3):
        assert np.array_equal(refine_alignment(new, ref, opts).env_from_new, res.env_from_new)


def test_alignment_with_nothing_to_align_is_not_applied_and_says_why() -> None:
    """No new points (say, a capture whose SGBM measured nothing near): identity, not applied,
    the reason names it (no ICP on an empty cloud)."""
    ref = np.random.default_rng(3).uniform(-1, 1, (1000, 3))
    for new in (np.zeros((0, 3)), np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.001]])):
        res = refine_alignment(new, ref, ReconstructOptions())
        assert not res.applied and "too few points to align" in res.reason
        np.testing.assert_array_equal(res.env_from_new, np.eye(4))
