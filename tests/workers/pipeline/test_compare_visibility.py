"""Re-projection with visibility, and "not seen ≠ removed"."""

from __future__ import annotations

import numpy as np
import pytest

from tests.workers.pipeline.compare_scene import (
    CLASSES,
    DIAMETERS,
    Counter,
    bin_,
    capture,
    crate,
    look_at,
    ring_cameras,
    twin_of,
)
from workers.pipeline.compare import PRESETS, Camera, compare_snapshots
from workers.pipeline.compare.visibility import (
    box_from_pixels,
    depth_votes,
    photo_agreement,
    project_in_image,
    render_depth,
    visible_points,
)


def wall(seed: int) -> np.ndarray:
    """A 1.2 m × 1.5 m wall in the plane x = 1.2 (between camera img00 and the origin)."""
    rng = np.random.default_rng(seed)
    uv = rng.random((int(4000 * 1.8), 2))
    return np.column_stack([np.full(len(uv), 1.2), -0.6 + 1.2 * uv[:, 0], 1.5 * uv[:, 1]])


def test_point_behind_a_wall_is_not_visible() -> None:
    k = np.array([[400.0, 0, 320], [0, 400, 240], [0, 0, 1]])
    front = Camera("front", k, 640, 480, look_at((3, 0, 1), (0, 0, 0.5)))
    back = Camera("back", k, 640, 480, look_at((-3, 0, 1), (0, 0, 0.5)))
    target = np.array([[0.0, 0.0, 0.5], [0.05, 0.0, 0.6]])
    cloud = np.concatenate([wall(0), target]).astype(np.float32)
    for cam, seen in ((front, False), (back, True)):
        dm = render_depth(cam, cloud, max_side=256, fill_px=1)
        assert dm.depth.shape == (192, 256)
        _, vis = visible_points(cam, target, dm)
        assert vis.tolist() == [seen, seen]
        _, vis_no_occlusion = visible_points(cam, target, None)
        assert vis_no_occlusion.all()
    # the wall itself is visible from the front camera
    dm = render_depth(front, cloud)
    _, vis = visible_points(front, wall(1)[:200], dm)
    assert vis.mean() > 0.95


def test_seen_empty_needs_a_surface_behind() -> None:
    k = np.array([[400.0, 0, 320], [0, 400, 240], [0, 0, 1]])
    cam = Camera("c", k, 640, 480, look_at((3, 0, 1), (0, 0, 0.5)))
    old_points = np.array([[0.0, 0.0, 0.5], [0.0, 0.0, 0.5], [0.0, 0.0, 0.5]])
    behind = wall(0) - [3.0, 0, 0]  # new surface at x = −1.8: behind → seen empty
    in_front = wall(0)  # new surface at x = 1.2: in front → occluded, unknown
    counts = [
        depth_votes(old_points[:1], [render_depth(cam, c.astype(np.float32))])[0][0]
        for c in (behind, in_front, np.zeros((0, 3)))  # none: nothing seen → unknown
    ]
    assert counts == [1, 0, 0]


def _photo(cam: Camera, cloud: np.ndarray, colours: np.ndarray) -> np.ndarray:
    """What ``cam`` photographs of a coloured cloud: each pixel the colour of the nearest
    point splatted there (a 5 × 5 splat, gaps grey), (h, w, 3) RGB in [0, 1]."""
    uv, z, inside = project_in_image(cam, cloud)
    photo = np.full((cam.height, cam.width, 3), 0.5, np.float32)
    zbuf = np.full((cam.height, cam.width), np.inf)
    for i in np.argsort(-z):
        if inside[i]:
            x, y = int(uv[i, 0]), int(uv[i, 1])
            rows, cols = slice(max(0, y - 2), y + 3), slice(max(0, x - 2), x + 3)
            closer = zbuf[rows, cols] > z[i]
            photo[rows, cols][closer] = colours[i]
            zbuf[rows, cols][closer] = z[i]
    return photo


def test_the_photo_vetoes_a_view_through_what_the_cloud_misses() -> None:
    """A red box stands in front of a blue wall; the cloud lost the box. The z-buffer then
    shows the wall through the box's place, but the photo shows red there: no camera saw
    that place empty. Where nothing stands, the photo shows the wall: seen empty."""
    k = np.array([[400.0, 0, 320], [0, 400, 240], [0, 0, 1]])
    cam = Camera("c", k, 640, 480, look_at((3, 0, 1), (0, 0, 0.5)))
    back = wall(0) - [3.0, 0, 0]  # the wall at x = −1.8, behind the box
    rng = np.random.default_rng(1)
    box = rng.uniform([-0.1, -0.1, 0.4], [0.1, 0.1, 0.6], (3000, 3))
    blue, red = np.array([0.1, 0.2, 0.8]), np.array([0.9, 0.1, 0.1])
    photo = _photo(cam, np.concatenate([back, box]), np.array([blue] * len(back) + [red] * 3000))
    cloud, cloud_colours = back.astype(np.float32), np.tile(blue, (len(back), 1)).astype(np.float32)
    dm = render_depth(cam, cloud, colors=cloud_colours, photo=photo * 0.8, colour_tolerance=0.1)
    assert dm.photo_agrees is not None
    inside_box, beside_box = np.array([[0.0, 0.0, 0.5]]), np.array([[0.0, 0.25, 0.5]])
    assert depth_votes(inside_box, [dm])[0][0] == 0
    assert depth_votes(beside_box, [dm])[0][0] == 1
    # depth alone (no photo) sees both places empty
    blind = render_depth(cam, cloud, colors=cloud_colours)
    assert blind.photo_agrees is None
    assert depth_votes(np.concatenate([inside_box, beside_box]), [blind])[0].tolist() == [1, 1]


def test_photo_agreement_matches_gains_and_lets_empty_pixels_through() -> None:
    rng = np.random.default_rng(0)
    colours = rng.uniform(0.2, 0.8, (40 * 50, 3)).astype(np.float32)
    index = np.arange(40 * 50).reshape(40, 50)
    index[:5] = -1  # no surface: nothing to contradict
    photo = colours[np.maximum(index, 0)] / np.array([1.25, 1.0, 0.8], np.float32)  # exposure
    photo[:5] = 0.0
    photo[20, 20] = [1.0, 0.0, 0.0]
    agrees = photo_agreement(index, colours, photo, 0.05)
    assert agrees[:5].all()
    assert not agrees[20, 20]
    assert agrees.sum() == agrees.size - 1


def test_robust_box_ignores_stray_points() -> None:
    uv = np.column_stack([np.linspace(0, 100, 1000), np.linspace(0, 50, 1000)])
    uv = np.concatenate([uv, [[5000.0, 5000.0]]])
    box = box_from_pixels(uv, 2.0)
    assert box[2] < 100 and box[3] < 50 and box[0] > 0
    np.testing.assert_allclose(box_from_pixels(uv, 0.0), [0, 0, 5000, 5000])


def test_occluded_cluster_has_no_box_in_the_blocked_camera() -> None:
    cams = ring_cameras()
    base = [crate(-0.8, 0.9), bin_(-0.6, -0.9)]
    new = [*base, crate(0.0, 0.0)]
    before = capture(base, cams, 1, extra=wall(11))
    after = capture(new, cams, 2, extra=wall(12))
    res = compare_snapshots(before, after, [], CLASSES, DIAMETERS, new_id=Counter())
    added = [c for c in res.clusters if c.side == "added" and c.object_name == "crate"]
    assert len(added) == 1
    assert "img00" not in added[0].boxes  # img00 at (3, 0, 2) looks through the wall
    assert {"img01", "img04", "img07"} <= set(added[0].boxes)
    thesis = compare_snapshots(before, after, [], CLASSES, DIAMETERS, PRESETS["thesis"])
    (added_thesis,) = [c for c in thesis.clusters if c.side == "added" and c.n_points > 1000]
    assert "img00" in added_thesis.boxes  # the thesis's method ignored occlusion


def test_geometry_the_new_cameras_did_not_see_is_not_removed() -> None:
    old_cams = ring_cameras()
    # the new capture only covers x ≤ 0.1 (cloud) with cameras around (−1, 0)
    new_cams = ring_cameras(6, radius=1.8, height=1.5, target=(-1, 0, 0), prefix="new")
    base = [crate(-0.8, 0.5), bin_(0.9, -0.6)]
    before = capture(base, old_cams, 1)
    after = capture([], new_cams, 2, x_range=(-2.0, 0.1))
    twin = twin_of(base, ["c1", "b1"])
    res = compare_snapshots(before, after, twin, CLASSES, DIAMETERS, new_id=Counter())
    removed = [c for c in res.changes if c.cluster.side == "removed"]
    assert [(c.type, c.object_name, c.instance_id) for c in removed] == [("removed", "crate", "c1")]
    assert all(c.centroid[0] < 0.1 for c in res.clusters if c.side == "removed")
    # without the check, the unseen bin and floor come back as removed geometry
    unchecked = PRESETS["default"].replace(check_seen_removed=False)
    res2 = compare_snapshots(before, after, twin, CLASSES, DIAMETERS, unchecked)
    assert any(c.side == "removed" and c.centroid[0] > 0.3 for c in res2.clusters)


@pytest.mark.parametrize("n", [1, 2, 7, 500])
@pytest.mark.parametrize("p", [0.5, 2.0, 25.0])
def test_box_percentiles_equal_numpy(n: int, p: float) -> None:
    uv = np.random.default_rng(n).uniform(0, 800, (n, 2))
    lo, hi = np.percentile(uv, [p, 100 - p], axis=0)
    np.testing.assert_allclose(box_from_pixels(uv, p), [lo[0], lo[1], hi[0], hi[1]], atol=1e-9)
