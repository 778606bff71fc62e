"""CPU multi-view stereo: neighbour selection, rectified SGBM per pair, per-view depth maps,
and a geometric consistency filter across views.

Everything is in the env frame, metres, OpenCV camera axes. Images are undistorted and
scaled first (:func:`working_scale`: ``mvs_scale``, bounded by ``mvs_max_image_size``);
depth maps live on that scaled pinhole grid.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from workers.pipeline.errors import ShapeError
from workers.pipeline.geometry import Mat4, invert_rigid
from workers.pipeline.reconstruct.cameras import CameraView
from workers.pipeline.reconstruct.common import Progress, no_progress, read_image
from workers.pipeline.reconstruct.errors import DenseReconstructionFailed
from workers.pipeline.reconstruct.options import ReconstructOptions

log = logging.getLogger(__name__)
FloatArray = NDArray[np.float64]
_SGBM_MODES = {
    "hh4": cv2.STEREO_SGBM_MODE_HH4,
    "3way": cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    "sgbm": cv2.STEREO_SGBM_MODE_SGBM,
    "hh": cv2.STEREO_SGBM_MODE_HH,
}


@dataclass(frozen=True)
class DenseView:
    """One undistorted, scaled pinhole view: BGR image (H, W, 3), K (3, 3), env_from_cam."""

    name: str
    image: NDArray[np.uint8]
    k_matrix: FloatArray
    env_from_cam: Mat4

    @property
    def cam_from_env(self) -> Mat4:
        return invert_rigid(self.env_from_cam)

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return int(self.image.shape[1]), int(self.image.shape[0])


@dataclass(frozen=True)
class Neighbours:
    """Per view: stereo partners, consistency neighbours, far-range partners and far-range
    partners whose depths only serve plane detection (indices; ``far`` and ``far_seed`` may
    be empty: no such pairs)."""

    stereo: tuple[tuple[int, ...], ...]
    consistency: tuple[tuple[int, ...], ...]
    far: tuple[tuple[int, ...], ...] = ()
    far_seed: tuple[tuple[int, ...], ...] = ()


def working_scale(width: int, height: int, scale: float, max_image_size: int) -> float:
    """Scale of a width×height (px) image's depth map: ``scale``, lowered so the long side
    is at most ``max_image_size`` px (-1: no bound)."""
    if max_image_size <= 0:
        return scale
    return min(scale, max_image_size / max(width, height))


def load_dense_views(
    images_dir: Path, views: tuple[CameraView, ...], scale: float, max_image_size: int = -1
) -> list[DenseView]:
    """Read, undistort and rescale (:func:`working_scale`) each view's image in turn, so only
    the scaled images are held; K follows (pixel centres kept)."""
    out = []
    for v in views:
        img = read_image(Path(images_dir) / v.name)
        k = v.intrinsics.k_matrix
        dist = v.intrinsics.dist_coeffs
        if img.shape[1] != v.intrinsics.width or img.shape[0] != v.intrinsics.height:
            raise ShapeError(
                f"{v.name} is {img.shape[1]}×{img.shape[0]}, its camera says "
                f"{v.intrinsics.width}×{v.intrinsics.height}"
            )
        if np.any(dist):
            img = np.asarray(cv2.undistort(img, k, dist), dtype=np.uint8)
        s = working_scale(img.shape[1], img.shape[0], scale, max_image_size)
        if s != 1.0:
            w, h = round(img.shape[1] * s), round(img.shape[0] * s)
            img = np.asarray(cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA), np.uint8)
            sx, sy = w / v.intrinsics.width, h / v.intrinsics.height
            k = k.copy()
            k[0, 0] *= sx
            k[1, 1] *= sy
            k[0, 2] = (k[0, 2] + 0.5) * sx - 0.5
            k[1, 2] = (k[1, 2] + 0.5) * sy - 0.5
        out.append(DenseView(v.name, np.ascontiguousarray(img), k, v.env_from_cam))
    return out


def _axis(view: DenseView) -> FloatArray:
    return np.asarray(view.env_from_cam[:3, 2], dtype=np.float64)


def select_neighbours(
    views: list[DenseView],
    points_env: FloatArray,
    visibility: NDArray[np.bool_],
    options: ReconstructOptions,
) -> Neighbours:
    """Choose stereo partners and consistency neighbours from shared sparse points.

    A stereo partner must share ≥ 30 points, see them under a median triangulation angle ≥
    ``min_triangulation_angle_deg`` and have its optical axis within
    ``max_viewing_angle_deg``; partners are ranked by shared points × angle weight
    (saturating at 15°), those whose sparse depth range fits in ``max_disparities`` at the
    pair's baseline first (SGBM finds nothing outside its window). Each view gets
    ``pairs_per_view`` partners of its own: a partner that already chose it is skipped,
    since that pair's one SGBM run gives depth to both. Consistency neighbours are the views
    sharing the most points.
    """
    n = len(views)
    if visibility.shape != (len(points_env), n):
        raise ShapeError(f"visibility must be ({len(points_env)}, {n}), got {visibility.shape}")
    centres = np.stack([v.env_from_cam[:3, 3] for v in views])
    axes = np.stack([_axis(v) for v in views])
    focal = [float(v.k_matrix[0, 0]) for v in views]
    vis = visibility.astype(np.float32)
    shared = vis.T @ vis
    stereo: list[tuple[int, ...]] = []
    consist: list[tuple[int, ...]] = []
    for i in range(n):
        scores: list[tuple[float, float, int]] = []
        for j in range(n):
            if j == i or shared[i, j] < 30:
                continue
            mask = visibility[:, i] & visibility[:, j]
            p = points_env[mask]
            a = p - centres[i]
            b = p - centres[j]
            cosang = np.sum(a * b, axis=1) / (
                np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1) + 1e-12
            )
            tri = float(np.degrees(np.arccos(np.clip(np.median(cosang), -1.0, 1.0))))
            view_angle = float(np.degrees(np.arccos(np.clip(axes[i] @ axes[j], -1.0, 1.0))))
            if (
                tri < options.min_triangulation_angle_deg
                or view_angle > options.max_viewing_angle_deg
            ):
                continue
            weight = min(tri / 15.0, 1.0) ** 2
            # a partner whose sparse depth range needs more disparities than SGBM searches
            # loses the surface outside its window: rank those after every one that fits
            depth = np.linalg.norm(a, axis=1)
            baseline_px = focal[i] * float(np.linalg.norm(centres[j] - centres[i]))
            far, near = _window_ends(
                baseline_px / np.percentile(depth, 99), baseline_px / np.percentile(depth, 1)
            )
            fits = near - far <= options.max_disparities
            scores.append((float(fits), float(shared[i, j]) * weight, j))
        scores.sort(reverse=True)
        # a pair runs once and gives depth to both views: skip partners that already chose i
        own = [j for _, _, j in scores if j >= i or i not in stereo[j]]
        stereo.append(tuple(own[: options.pairs_per_view]))
        order = [int(j) for j in np.argsort(-shared[i]) if j != i and shared[i, j] >= 10]
        consist.append(tuple(order[: options.consistency_views]))
    far_pairs = _far_partners(centres, axes, shared, options)
    far_seed = _far_seed_partners(centres, axes, shared, far_pairs, options)
    return Neighbours(tuple(stereo), tuple(consist), far_pairs, far_seed)


def _far_partners(
    centres: FloatArray, axes: FloatArray, shared: NDArray[np.float32], options: ReconstructOptions
) -> tuple[tuple[int, ...], ...]:
    """Per view at most one far-range partner: the widest baseline among the views sharing ≥
    30 sparse points with optical axes within ``far_max_axis_angle_deg``, among the views
    not yet in a far pair when there are any. A view that is already the far partner of an
    earlier view gets none of its own (that pair gives depth to both), so there are about
    half as many far pairs as views."""
    n = len(centres)
    if not options.far_range:
        return tuple(() for _ in range(n))
    far: list[tuple[int, ...]] = []
    covered: set[int] = set()
    for i in range(n):
        if i in covered:
            far.append(())
            continue
        ok = _far_candidates(i, axes, shared, options)
        if not ok.any():
            far.append(())
            continue
        free = ok.copy()
        free[list(covered)] = False
        if free.any():  # a partner without a far pair of its own gets one from this pair
            ok = free
        j = _widest(i, ok, centres)
        far.append((j,))
        covered.update((i, j))
    return tuple(far)


def _far_seed_partners(
    centres: FloatArray,
    axes: FloatArray,
    shared: NDArray[np.float32],
    far: tuple[tuple[int, ...], ...],
    options: ReconstructOptions,
) -> tuple[tuple[int, ...], ...]:
    """Per view without a far partner of its own (the partner of an earlier view's far
    pair), one for the planar prior's plane detection only: the widest baseline with optical
    axes within ``far_max_axis_angle_deg`` among the views not already in a far pair with it
    sharing ≥ 30 sparse points. Their depths are not fused into the cloud.

    A far depth needs a second pair to confirm it, since a pair's own two views agree by
    construction: with one far pair per two views, a far wall that only a few views see
    along their image edges had one pair's depth and no seed point, so no plane. Their
    depths stay out of the cloud: fused, they lowered the floor's completeness (far SGBM
    depth 1-4 cm off kept where the verified plane would have filled in; figures in
    docs/decisions/reconstruct.md)."""
    n = len(centres)
    if not options.far_range or not options.planar_prior:
        return tuple(() for _ in range(n))
    paired = {(min(i, j), max(i, j)) for i, js in enumerate(far) for j in js}
    out: list[tuple[int, ...]] = []
    for i in range(n):
        ok = np.zeros(n, np.bool_) if far[i] else _far_candidates(i, axes, shared, options)
        for k in map(int, np.flatnonzero(ok)):
            ok[k] = (min(i, k), max(i, k)) not in paired
        if not ok.any():
            out.append(())
            continue
        j = _widest(i, ok, centres)
        out.append((j,))
        paired.add((min(i, j), max(i, j)))
    return tuple(out)


def _far_candidates(
    i: int, axes: FloatArray, shared: NDArray[np.float32], options: ReconstructOptions
) -> NDArray[np.bool_]:
    """(V,) the views that may be view i's far-range partner: sharing ≥ 30 sparse points
    with it, optical axes within ``far_max_axis_angle_deg`` of its own, not i itself."""
    ok = (axes @ axes[i] >= np.cos(np.radians(options.far_max_axis_angle_deg))) & (shared[i] >= 30)
    ok[i] = False
    return np.asarray(ok)


def _widest(i: int, ok: NDArray[np.bool_], centres: FloatArray) -> int:
    """The view of mask ``ok`` (any set) whose centre is farthest from view i's."""
    return int(np.argmax(np.where(ok, np.linalg.norm(centres - centres[i], axis=1), -1.0)))


def with_far_confirming_neighbours(
    views: list[DenseView],
    depths: list[NDArray[np.float32]],
    neighbours: Neighbours,
    options: ReconstructOptions,
    stride: int = 8,
    min_confirmed: int = 50,
) -> Neighbours:
    """``neighbours`` with each view's consistency neighbours extended by up to
    ``consistency_views`` more: the views whose depth maps confirm the most of its far
    depths (≥ ``far_min_depth_m``, every ``stride``-th pixel, within
    ``far_consistency_rel_tol``), at least ``min_confirmed`` of them.

    The consistency neighbours share the most sparse points, which lie on the scene's
    centre; a far wall that a few views see along their image edges is seen by other views
    than those, and its far depths found no second agreeing view.
    """
    if len(views) != len(depths):
        raise ShapeError(f"{len(views)} views but {len(depths)} depth maps")
    out: list[tuple[int, ...]] = []
    tol = np.float32(options.far_consistency_rel_tol)
    for i, view in enumerate(views):
        far = np.where(depths[i] >= options.far_min_depth_m, depths[i], 0.0).astype(np.float32)
        pts, _ = backproject(view, far, stride)
        own = neighbours.consistency[i]
        counts: list[tuple[int, int]] = []
        if len(pts):
            rel_tol = np.full(len(pts), tol, np.float32)
            for j in range(len(views)):
                if j == i or j in own:
                    continue
                n_ok = int(_agreement(views, depths, pts, rel_tol, (j,))[0].sum())
                if n_ok >= min_confirmed:
                    counts.append((n_ok, j))
        counts.sort(reverse=True)
        out.append(tuple(own) + tuple(j for _, j in counts[: options.consistency_views]))
    return dataclasses.replace(neighbours, consistency=tuple(out))


def _ceil16(v: float) -> int:
    return int(np.ceil(v / 16.0) * 16)


def _window_ends(low_px: float, high_px: float) -> tuple[float, float]:
    """(far, near) disparity ends in px around the sparse points' 1st and 99th percentile
    disparities ``low_px`` and ``high_px``: × 0.85 − 2 px and × 1.15 + 2 px of margin."""
    return low_px * 0.85 - 2.0, high_px * 1.15 + 2.0


def disparity_window(disparities: FloatArray, max_disparities: int) -> tuple[int, int]:
    """SGBM (minDisparity, numDisparities) for a pair from its sparse points' disparities (px).

    The near end is the 99th percentile × 1.15 + 2 px. The window spends the whole budget of
    ``max_disparities`` below it (down to 0 = infinity), since sparse points under-sample far,
    weakly textured surfaces (walls, far floor). When the sparse 1–99 % span (× 0.85 / 1.15)
    is wider than the budget, the window holds the most sparse points instead.
    """
    d = np.sort(np.asarray(disparities, dtype=np.float64))
    far, near = _window_ends(float(np.percentile(d, 1)), float(np.percentile(d, 99)))
    far = max(0.0, far)
    if near - far <= max_disparities:
        min_disp = max(0, int(np.ceil(near)) - max_disparities)
        return min_disp, max(16, min(max_disparities, _ceil16(near - min_disp)))
    starts = np.floor(d).astype(np.int64)
    inside = np.searchsorted(d, starts + max_disparities, side="left") - np.arange(len(d))
    min_disp = int(starts[int(np.argmax(inside))])
    log.info("disparity span %.0f-%.0f px over the budget: window from %d", far, near, min_disp)
    return max(min_disp, 0), max_disparities


def nearer_window(
    disparities: FloatArray, first: tuple[int, int], max_disparities: int
) -> tuple[int, int] | None:
    """A second SGBM (minDisparity, numDisparities) for the sparse points (px) nearer than
    ``first``'s near end, when over 1 % of them (and ≥ 5) are: it starts 16 px below that
    end and spends up to ``max_disparities`` towards their 99th percentile × 1.15 + 2 px.
    None when ``first`` holds them (a near surface seen past a far one fits one window)."""
    d = np.asarray(disparities, dtype=np.float64)
    top = first[0] + first[1]
    nearer = d[d >= top]
    if len(nearer) < max(5, 0.01 * len(d)):
        return None
    start = max(0, top - 16)
    _, near = _window_ends(float(np.min(nearer)), float(np.percentile(nearer, 99)))
    return start, max(16, min(max_disparities, _ceil16(near - start)))


def far_disparity_window(focal_baseline: float, min_depth_m: float, num: int) -> tuple[int, int]:
    """SGBM (minDisparity, numDisparities) of a far-range pair: ``num`` disparities below
    that of ``min_depth_m`` (``focal_baseline`` / ``min_depth_m``, px), down to 0 (infinity)
    at most. Not from the sparse points: those a wide pair shares are mostly near ones, and
    far, weakly textured walls have few."""
    near = int(np.ceil(focal_baseline / min_depth_m))
    return max(0, near - num), num


def fit_window(window: tuple[int, int], width_px: int, block_px: int) -> tuple[int, int] | None:
    """``window`` (minDisparity, numDisparities) cut to what a rectified grid ``width_px``
    wide can hold (a disparity beyond the width has no match; OpenCV's SGBM fails on such a
    window); None when fewer than 16 disparities remain."""
    min_disp, num = window
    room = (width_px - block_px - max(min_disp, 0)) // 16 * 16
    return None if room < 16 else (min_disp, min(num, room))


def _depth_from_disparity(
    disp: NDArray[np.float32],
    k_matrix: FloatArray,
    rect: FloatArray,
    proj: FloatArray,
    baseline: float,
) -> NDArray[np.float32]:
    """Depth (H, W) float32 metres (0 = unknown) of a view from its rectified disparity map
    (NaN = unknown); ``rect``/``proj`` are the view's R and P from stereoRectify.

    Pixel x maps to the rectified pixel P R K⁻¹ x (a homography); a point on the ray of x at
    camera depth λ has rectified depth λ (R K⁻¹ x)_z, so λ = (f b / d) / (R K⁻¹ x)_z.
    """
    h, w = disp.shape
    ray_rect = rect @ np.linalg.inv(k_matrix)
    rect_from_pix = proj[:, :3] @ ray_rect
    sampled = cv2.warpPerspective(
        disp,
        rect_from_pix,
        (w, h),
        flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=float("nan"),
    )
    a, b, c = ray_rect[2]
    z_factor = (
        a * np.arange(w, dtype=np.float32)[None, :]
        + b * np.arange(h, dtype=np.float32)[:, None]
        + c
    )
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = np.float32(float(proj[0, 0]) * baseline) / (sampled * z_factor)
    return np.where(np.isfinite(depth) & (depth > 0), depth, 0.0).astype(np.float32)


def _right_disparity(disp_left: NDArray[np.float32]) -> NDArray[np.float32]:
    """The right image's disparity map (NaN = unknown) from the left one of a rectified pair.

    Left pixel x with disparity d lands at x - d in the right image; between two horizontal
    neighbours on one surface (|Δd| ≤ 1 px) the disparity is interpolated linearly onto the
    integer right pixels they span, and the nearest surface (largest d) wins.
    """
    h, w = disp_left.shape
    d0, d1 = disp_left[:, :-1], disp_left[:, 1:]
    ok = np.isfinite(d0) & np.isfinite(d1) & (np.abs(d1 - d0) <= 1.0)
    ys, xs = np.nonzero(ok)
    a, b = d0[ys, xs].astype(np.float64), d1[ys, xs].astype(np.float64)
    s0 = xs - a  # right x of the left pixel x
    span = 1.0 - (b - a)  # right x of pixel x + 1 minus s0, in [0, 2]
    out = np.full(h * w, -np.inf)
    for step in (0, 1):
        u = np.ceil(s0) + step
        t = (u - s0) / np.maximum(span, 1e-6)
        m = (u < s0 + span) & (u >= 0) & (u < w)
        idx = ys[m] * w + u[m].astype(np.int64)
        np.maximum.at(out, idx, a[m] + t[m] * (b[m] - a[m]))
    out[~np.isfinite(out)] = np.nan
    return out.reshape(h, w).astype(np.float32)


def _textureless(gray: NDArray[np.uint8], block: int, min_std: float = 1.0) -> NDArray[np.bool_]:
    """Pixels whose ``block``² neighbourhood has an intensity std below ``min_std`` grey
    levels: SGBM's smoothness spreads a neighbour's disparity into them (no evidence)."""
    g = gray.astype(np.float32)
    mean = cv2.boxFilter(g, -1, (block, block))
    sq = cv2.boxFilter(g * g, -1, (block, block))
    return np.asarray(sq - mean * mean < min_std * min_std, dtype=np.bool_)


@dataclass(frozen=True)
class _Rectification:
    """A stereo pair's rectification (cv2.stereoRectify): per view R (3, 3) and P (3, 4),
    whether the pair is ``vertical`` (its baseline along y) and ``flip``ped (src left of or
    above ref), focal ``f_px`` and ``baseline_m``. Canonical images are the rectified ones
    transposed and mirrored so that ref is the left image of a horizontal pair."""

    r_ref: FloatArray
    r_src: FloatArray
    p_ref: FloatArray
    p_src: FloatArray
    vertical: bool
    flip: bool
    f_px: float
    baseline_m: float

    def canon(self, img: NDArray[Any]) -> NDArray[Any]:
        out = img.T if self.vertical else img
        return np.ascontiguousarray(out[:, ::-1] if self.flip else out)

    def uncanon(self, img: NDArray[Any]) -> NDArray[Any]:
        out = img[:, ::-1] if self.flip else img
        return np.ascontiguousarray(out.T if self.vertical else out)


def _rectify(ref: DenseView, src: DenseView) -> _Rectification:
    w, h = ref.size
    src_from_ref = src.cam_from_env @ ref.env_from_cam
    rot = np.ascontiguousarray(src_from_ref[:3, :3])
    trans = np.ascontiguousarray(src_from_ref[:3, 3].reshape(3, 1))
    r1, r2, p1, p2, _, _, _ = (
        np.asarray(m, np.float64)
        for m in cv2.stereoRectify(
            ref.k_matrix,
            np.zeros(5),
            src.k_matrix,
            np.zeros(5),
            (w, h),
            rot,
            trans,
            flags=cv2.CALIB_ZERO_DISPARITY,
            alpha=-1,
        )
    )
    vertical = abs(p2[1, 3]) > abs(p2[0, 3])
    tx = p2[1, 3] if vertical else p2[0, 3]
    f = float(p1[0, 0])
    # flip: src lies left (or above) of ref in the rectified frame
    return _Rectification(r1, r2, p1, p2, bool(vertical), bool(tx > 0), f, abs(float(tx)) / f)


def _sgbm_windows(
    ref: DenseView,
    rect: _Rectification,
    points_env: FloatArray,
    options: ReconstructOptions,
    far_range: bool,
) -> list[tuple[int, int]]:
    """SGBM (minDisparity, numDisparities) windows of the pair from its (N, 3) shared sparse
    points: :func:`disparity_window` and, where it leaves near points out,
    :func:`nearer_window`; :func:`far_disparity_window` alone with ``far_range``. Empty when
    fewer than 5 of them lie in front of the rectified ref camera."""
    p_cam = points_env @ ref.cam_from_env[:3, :3].T + ref.cam_from_env[:3, 3]
    z_rect = (p_cam @ rect.r_ref.T)[:, 2]
    z_rect = z_rect[z_rect > 1e-6]
    if len(z_rect) < 5:
        return []
    f, baseline = rect.f_px, rect.baseline_m
    if far_range:
        return [
            far_disparity_window(f * baseline, options.far_min_depth_m, options.far_max_disparities)
        ]
    disparities = f * baseline / z_rect
    first = disparity_window(disparities, options.max_disparities)
    second = nearer_window(disparities, first, options.max_disparities)
    return [first] if second is None else [first, second]


@dataclass(frozen=True)
class _RectifiedView:
    """One view of a pair on the canonical rectified grid: ``gray`` (h, w) uint8, ``valid``
    (h, w) bool (inside the source image), and ``rows`` (h,) bool, the rows worth matching
    for a far-range pair (None: no near depths given)."""

    gray: NDArray[np.uint8]
    valid: NDArray[np.bool_]
    rows: NDArray[np.bool_] | None


def _rectified_view(
    view: DenseView,
    r: FloatArray,
    p: FloatArray,
    rect: _Rectification,
    near: NDArray[np.float32] | None,
    options: ReconstructOptions,
) -> _RectifiedView:
    """``view`` remapped by its rectification R ``r``, P ``p``; with ``near`` (its (H, W)
    near-range depth map) the rows where its known depths are ≥ 5 % beyond 0.8 ×
    ``far_min_depth_m`` (every row inside the image when it knows < 20 % of its pixels)."""
    w, h = view.size
    m1, m2 = cv2.initUndistortRectifyMap(view.k_matrix, np.zeros(5), r, p, (w, h), cv2.CV_32FC1)
    gray = cv2.cvtColor(view.image, cv2.COLOR_BGR2GRAY)
    rect_gray = rect.canon(np.asarray(cv2.remap(gray, m1, m2, cv2.INTER_LINEAR), np.uint8))
    inside = cv2.remap(np.full((h, w), 255, np.uint8), m1, m2, cv2.INTER_NEAREST)
    valid = rect.canon(np.asarray(inside, np.uint8)) > 0
    if near is None:
        return _RectifiedView(rect_gray, valid, None)
    counts = []
    for mask in (near > 0, near >= 0.8 * options.far_min_depth_m):
        warped = cv2.remap(mask.astype(np.uint8), m1, m2, cv2.INTER_NEAREST)
        counts.append(rect.canon(np.asarray(warped, np.uint8)).sum(axis=1))
    inside_n = valid.sum(axis=1)
    if counts[0].sum() < 0.2 * inside_n.sum():  # too little known: match every row
        rows = inside_n > 0
    else:
        rows = (counts[1] >= 0.05 * np.maximum(counts[0], 1)) & (counts[1] > 0)
    return _RectifiedView(rect_gray, valid, rows)


def _sgbm_disparity(
    left: _RectifiedView,
    right: _RectifiedView,
    window: tuple[int, int],
    rows_used: slice,
    near_end_outside: bool,
    options: ReconstructOptions,
) -> NDArray[np.float32]:
    """The left canonical disparity map in px (NaN = unknown) of one SGBM run over
    ``rows_used``: matches at the window's far end (and its near end with
    ``near_end_outside``: surfaces nearer than it exist), outside the images or in
    textureless windows are dropped."""
    min_disp, num = window
    bs = options.sgbm_block_size
    sgbm = cv2.StereoSGBM.create(
        minDisparity=min_disp,
        numDisparities=num,
        blockSize=bs,
        P1=8 * bs * bs,
        P2=32 * bs * bs,
        disp12MaxDiff=1,
        uniquenessRatio=10,
        speckleWindowSize=100,
        speckleRange=2,
        mode=_SGBM_MODES[options.sgbm_mode],
    )
    # SGBM leaves the left image's first minDisparity + numDisparities columns unmatched
    # (their whole search range would start left of the right image): pad both on the left
    # by as much, so every left pixel whose match lies in the right image is searched
    pad = max(min_disp, 0) + num
    disp = np.full(left.gray.shape, -1.0, np.float32)
    disp[rows_used] = sgbm.compute(
        cv2.copyMakeBorder(left.gray[rows_used], 0, 0, pad, 0, cv2.BORDER_CONSTANT, value=0),
        cv2.copyMakeBorder(right.gray[rows_used], 0, 0, pad, 0, cv2.BORDER_CONSTANT, value=0),
    )[:, pad:].astype(np.float32)
    disp /= 16.0
    # matches at either end of the window are surfaces outside it; a match left of the
    # right image's first block is one into the padding
    at_ends = (disp <= max(min_disp, 0) + 0.5) | (near_end_outside & (disp >= min_disp + num - 1.5))
    outside = np.arange(left.gray.shape[1], dtype=np.float32)[None, :] - disp < bs
    disp[at_ends | outside | ~left.valid | _textureless(left.gray, bs)] = np.nan
    return disp


def box_mean(img: NDArray[np.float32], win: int) -> NDArray[np.float32]:
    """The mean of each ``win``² window of an (h, w) float32 image (edges reflected)."""
    return np.asarray(cv2.boxFilter(img, -1, (win, win), borderType=cv2.BORDER_REFLECT), np.float32)


@dataclass(frozen=True)
class WindowStats:
    """A grey image (h, w) float32 and its ZNCC windows' mean and variance."""

    gray: NDArray[np.float32]
    mean: NDArray[np.float32]
    var: NDArray[np.float32]

    @classmethod
    def of(cls, gray: NDArray[np.float32], win: int) -> WindowStats:
        """The stats of ``gray``'s ``win``² windows."""
        mean = box_mean(gray, win)
        return cls(gray, mean, box_mean(gray * gray, win) - mean * mean)


def zncc(ref: WindowStats, warped: NDArray[np.float32], win: int) -> NDArray[np.float32]:
    """(h, w) ZNCC (-1..1; about 0 where either side is flat) of ``win``² windows of the
    reference and a warped (h, w) grey image."""
    mean_w = box_mean(warped, win)
    var_w = box_mean(warped * warped, win) - mean_w * mean_w
    cov = box_mean(ref.gray * warped, win) - ref.mean * mean_w
    return np.asarray(cov / np.sqrt(np.maximum(ref.var * var_w, 1e-6)), np.float32)


def _shifted_right(right: NDArray[np.uint8], disp: NDArray[np.float32]) -> NDArray[np.float32]:
    """The right grey image sampled at each left pixel's match, x - ``disp`` (px), as float32
    (a NaN disparity samples the border: 0)."""
    h, w = right.shape
    xs = np.arange(w, dtype=np.float32)[None, :] - np.nan_to_num(disp, nan=-1e4)
    ys = np.broadcast_to(np.arange(h, dtype=np.float32)[:, None], (h, w))
    sampled = cv2.remap(right.astype(np.float32), xs, np.ascontiguousarray(ys), cv2.INTER_LINEAR)
    return np.asarray(sampled, np.float32)


def _merge_windows(
    left: NDArray[np.uint8],
    right: NDArray[np.uint8],
    far: NDArray[np.float32],
    near: NDArray[np.float32],
    block: int,
) -> NDArray[np.float32]:
    """One left disparity map (px, NaN = unknown) from two windows' runs on the canonical
    ``left``/``right`` grey images: a pixel matched in one takes that match; matched in both,
    the mean where they agree within 1 px (the windows overlap by 16 px), else the match
    whose ``block``² window correlates better (:func:`zncc`; the other is false)."""
    both = np.isfinite(far) & np.isfinite(near)
    out = np.where(np.isfinite(far), far, near)
    agree = both & (np.abs(far - near) <= 1.0)
    out[agree] = 0.5 * (far[agree] + near[agree])
    conflict = both & ~agree
    if conflict.any():
        ref = WindowStats.of(left.astype(np.float32), block)
        nearer_wins = zncc(ref, _shifted_right(right, near), block) > zncc(
            ref, _shifted_right(right, far), block
        )
        out[conflict] = np.where(nearer_wins[conflict], near[conflict], far[conflict])
    return out.astype(np.float32)


def _rows_to_match(left: _RectifiedView, right: _RectifiedView) -> slice | None:
    """The canonical rows SGBM must match: all, or those either view wants, ± 8 (None:
    none is wanted)."""
    if left.rows is None or right.rows is None:
        return slice(0, left.gray.shape[0])
    want_rows = left.rows | right.rows
    idx = np.flatnonzero(want_rows)
    if len(idx) == 0:
        return None
    return slice(max(0, int(idx[0]) - 8), min(len(want_rows), int(idx[-1]) + 9))


def pair_depths(
    ref: DenseView,
    src: DenseView,
    points_env: FloatArray,
    options: ReconstructOptions,
    far_range: bool = False,
    near_depths: tuple[NDArray[np.float32], NDArray[np.float32]] | None = None,
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Depth maps (H, W) float32 in metres (0 = unknown) of ``ref`` and of ``src`` from one
    SGBM run on the rectified pair (two where one window cannot hold the near sparse points:
    :func:`nearer_window`); ``src``'s map is the ref disparity warped to it.
    ``points_env`` (N, 3) sparse points seen by both give the disparity range; with
    ``far_range`` the window only covers depths beyond ``far_min_depth_m``
    (:func:`far_disparity_window`). ``near_depths`` (the two views' depth maps from their
    near-range pairs) restrict the run to the rectified rows, ± 8, where either view's known
    depths are ≥ 5 % beyond 0.8 × ``far_min_depth_m`` (every row of a view with depth at
    fewer than 20 % of its pixels): SGBM's time is proportional to the rows it matches, and
    far surfaces lie in the upper half of views that look down at the scene.
    """
    w, h = ref.size
    if src.size != ref.size:
        raise ShapeError("stereo pairs must share an image size at MVS scale")
    rect = _rectify(ref, src)
    empty = np.zeros((h, w), np.float32)
    windows = _sgbm_windows(ref, rect, points_env, options, far_range)
    if not windows:
        return empty, empty.copy()
    near_ref, near_src = (None, None) if near_depths is None else near_depths
    left = _rectified_view(ref, rect.r_ref, rect.p_ref, rect, near_ref, options)
    right = _rectified_view(src, rect.r_src, rect.p_src, rect, near_src, options)
    rows_used = _rows_to_match(left, right)
    fitted = [fit_window(win, left.gray.shape[1], options.sgbm_block_size) for win in windows]
    if rows_used is None or fitted[0] is None:
        return empty, empty.copy()
    nearer = fitted[1] if len(fitted) > 1 else None
    near_end_outside = far_range or nearer is not None
    disp = _sgbm_disparity(left, right, fitted[0], rows_used, near_end_outside, options)
    if nearer is not None:
        disp_near = _sgbm_disparity(left, right, nearer, rows_used, True, options)
        disp = _merge_windows(left.gray, right.gray, disp, disp_near, options.sgbm_block_size)
    disp_src = _right_disparity(disp)
    disp_src[~right.valid | _textureless(right.gray, options.sgbm_block_size)] = np.nan
    return (
        _depth_from_disparity(
            rect.uncanon(disp), ref.k_matrix, rect.r_ref, rect.p_ref, rect.baseline_m
        ),
        _depth_from_disparity(
            rect.uncanon(disp_src), src.k_matrix, rect.r_src, rect.p_src, rect.baseline_m
        ),
    )


@dataclass(frozen=True)
class DepthMaps:
    """Per view (H, W) float32 depth maps, metres (0 = unknown): ``fused``, from the stereo
    and far-range pairs (what the cloud is made of), and ``plane_seed``, with the
    ``far_seed`` pairs' depths laid over them too (for plane detection only; a view in no
    such pair has its ``fused`` map there)."""

    fused: list[NDArray[np.float32]]
    plane_seed: list[NDArray[np.float32]]


def compute_depth_maps(
    views: list[DenseView],
    neighbours: Neighbours,
    points_env: FloatArray,
    visibility: NDArray[np.bool_],
    options: ReconstructOptions,
    progress: Progress = no_progress,
) -> DepthMaps:
    """One (H, W) float32 depth map per view (metres, 0 = unknown), and the plane-seed maps.

    Every stereo partnership is one undirected pair and one SGBM run, which gives depth to
    both of its views; a view in several pairs gets the per-pixel median of the valid
    estimates. The far-range pairs run after the near ones (they match only the rows where
    those see far or nothing) and are laid over them (:func:`_overlay_far`); so are the
    ``far_seed`` pairs, into the plane-seed maps only.
    """
    pairs = _undirected(neighbours.stereo)
    far_pairs = _undirected(neighbours.far)
    fused_far = set(far_pairs)
    seed_pairs = [p for p in _undirected(neighbours.far_seed) if p not in fused_far]
    n_jobs = len(pairs) + len(far_pairs) + len(seed_pairs)
    done = 0

    def run(
        pair_list: list[tuple[int, int]], far_range: bool, near: list[NDArray[np.float32]] | None
    ) -> list[list[NDArray[np.float32]]]:
        """Each view's depth estimates from the pairs of ``pair_list``."""
        nonlocal done
        est: list[list[NDArray[np.float32]]] = [[] for _ in views]
        for i, j in pair_list:
            mask = visibility[:, i] & visibility[:, j]
            near_ij = None if near is None else (near[i], near[j])
            depth_i, depth_j = pair_depths(
                views[i], views[j], points_env[mask], options, far_range, near_ij
            )
            est[i].append(depth_i)
            est[j].append(depth_j)
            done += 1
            progress("stereo", done / n_jobs)
        return est

    near = [
        _combine(est, view.image.shape[:2])
        for view, est in zip(views, run(pairs, False, None), strict=True)
    ]
    far_est = run(far_pairs, True, near)
    seed_est = run(seed_pairs, True, near)
    fused, plane_seed = [], []
    for view, depth, fest, sest in zip(views, near, far_est, seed_est, strict=True):
        shape = view.image.shape[:2]
        out = _overlay_far(depth, _combine(fest, shape), options) if fest else depth
        fused.append(out)
        plane_seed.append(
            _overlay_far(depth, _combine(fest + sest, shape), options) if sest else out
        )
    return DepthMaps(fused, plane_seed)


def _undirected(partners: tuple[tuple[int, ...], ...]) -> list[tuple[int, int]]:
    """The sorted undirected pairs (i < j) of per-view partner lists."""
    return sorted({(min(i, j), max(i, j)) for i, js in enumerate(partners) for j in js})


def _combine(est: list[NDArray[np.float32]], shape: tuple[int, ...]) -> NDArray[np.float32]:
    if not est:
        return np.zeros(shape[:2], np.float32)
    return est[0] if len(est) == 1 else _median_of_valid(np.stack(est))


def _overlay_far(
    near: NDArray[np.float32], far: NDArray[np.float32], options: ReconstructOptions
) -> NDArray[np.float32]:
    """A view's depth from its near-range pairs with the far-range pair's depth laid over it:
    the far pair's wider baseline wins wherever it has a depth, except where the near-range
    pairs see a surface nearer than ``far_min_depth_m`` (an occluder the far pair's window
    cannot hold, so its match there is spurious)."""
    use = (far > 0) & ~((near > 0) & (near < options.far_min_depth_m))
    return np.where(use, far, near).astype(np.float32)


def _median_of_valid(stack: NDArray[np.float32]) -> NDArray[np.float32]:
    """Per-pixel median of the valid (> 0) values of a (K, H, W) stack; 0 where none is."""
    if len(stack) == 2:  # the mean of two, or the one valid value (no sort)
        a, b = stack
        both = (a > 0) & (b > 0)
        return np.asarray(np.where(both, 0.5 * (a + b), np.maximum(a, b)), np.float32)
    valid = stack > 0
    n = valid.sum(axis=0)
    srt = np.sort(np.where(valid, stack, np.inf), axis=0)
    lo = np.take_along_axis(srt, (np.maximum(n - 1, 0) // 2)[None], axis=0)[0]
    hi = np.take_along_axis(srt, (n // 2)[None], axis=0)[0]
    return np.where(n > 0, 0.5 * (lo + hi), 0.0).astype(np.float32)


def backproject(
    view: DenseView, depth: NDArray[np.float32], stride: int = 1
) -> tuple[FloatArray, NDArray[np.int64]]:
    """Env-frame (M, 3) points of the valid pixels of ``depth`` (every ``stride``-th pixel)
    and their (M, 2) integer pixel coordinates (x, y)."""
    h, w = depth.shape
    ys, xs = np.mgrid[0:h:stride, 0:w:stride]
    z = depth[ys, xs].astype(np.float64)
    ok = z > 0
    xs, ys, z = xs[ok], ys[ok], z[ok]
    k = view.k_matrix
    p_cam = np.stack([(xs - k[0, 2]) * z / k[0, 0], (ys - k[1, 2]) * z / k[1, 1], z], axis=1)
    p_env = p_cam @ view.env_from_cam[:3, :3].T + view.env_from_cam[:3, 3]
    return p_env, np.stack([xs, ys], axis=1).astype(np.int64)


def _sample_depth(
    view: DenseView, depth: NDArray[np.float32], points_env: NDArray[np.float32]
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Project (N, 3) env points into ``view``: (their depth, the map's depth at the nearest
    pixel, 0 outside the image or behind the camera), both (N,) float32 metres."""
    cam_from_env = view.cam_from_env.astype(np.float32)
    p_cam = points_env @ cam_from_env[:3, :3].T + cam_from_env[:3, 3]
    z = p_cam[:, 2]
    k = view.k_matrix
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.rint(np.float32(k[0, 0]) * p_cam[:, 0] / z + np.float32(k[0, 2]))
        v = np.rint(np.float32(k[1, 1]) * p_cam[:, 1] / z + np.float32(k[1, 2]))
    h, w = depth.shape
    inside = (z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    d = np.zeros(len(z), np.float32)
    d[inside] = depth[v[inside].astype(np.int64), u[inside].astype(np.int64)]
    return z, d


@dataclass(frozen=True)
class VerifiedDepths:
    """Depths already verified photometrically (plane depths), one entry per view, for
    :func:`consistent_points_split`: ``masks`` (H, W) bool, the verified pixels;
    ``checked_by`` the views each view's verified depths were checked against (None: none);
    ``fallback`` (H, W) float32 metres (0 = none, None: no fallbacks), a verified depth for
    pixels that kept a measured one."""

    masks: list[NDArray[np.bool_]]
    checked_by: list[tuple[int, ...]] | None = None
    fallback: list[NDArray[np.float32]] | None = None


@dataclass(frozen=True)
class ConsistentPoints:
    """What :func:`consistent_points_split` keeps: ``points_env`` (M, 3) env-frame metres,
    ``colors_rgb`` (M, 3) uint8, ``verified`` (M,) bool (from a verified pixel or a fallback
    depth), ``depth_m`` (M,) float32 (the depth in metres the point had in its own view)."""

    points_env: FloatArray
    colors_rgb: NDArray[np.uint8]
    verified: NDArray[np.bool_]
    depth_m: NDArray[np.float32]


def consistent_points(
    views: list[DenseView],
    depths: list[NDArray[np.float32]],
    neighbours: Neighbours,
    options: ReconstructOptions,
    progress: Progress = no_progress,
) -> tuple[FloatArray, NDArray[np.uint8]]:
    """The (M, 3) points and (M, 3) RGB colours of :func:`consistent_points_split`."""
    out = consistent_points_split(views, depths, neighbours, options, progress)
    return out.points_env, out.colors_rgb


def _agreement(
    views: list[DenseView],
    depths: list[NDArray[np.float32]],
    points_env: FloatArray,
    rel_tol: NDArray[np.float32],
    others: tuple[int, ...],
) -> tuple[NDArray[np.int32], FloatArray]:
    """For (N, 3) env points: how many views of ``others`` have a depth that agrees with the
    point's depth in them within (N,) ``rel_tol`` (relative), and the sum (N, 3) of the
    point and those views' own measurements on the same ray."""
    pts32 = points_env.astype(np.float32)
    support = np.zeros(len(points_env), np.int32)
    acc = points_env.copy()
    for j in others:
        z, d = _sample_depth(views[j], depths[j], pts32)
        ok = (d > 0) & (np.abs(d - z) <= rel_tol * z)
        if not ok.any():
            continue
        support += ok
        # the neighbour's own measurement on the same ray of view j: c + (p - c) d / z
        centre = views[j].env_from_cam[:3, 3]
        scale = (d[ok] / z[ok]).astype(np.float64)
        acc[ok] += centre + (points_env[ok] - centre) * scale[:, None]
    return support, acc


@dataclass(frozen=True)
class _Consistency:
    """The inputs of one consistency check: the views, their (H, W) float32 depth maps
    (metres), neighbours, options and the verified depths (None: none)."""

    views: list[DenseView]
    depths: list[NDArray[np.float32]]
    neighbours: Neighbours
    options: ReconstructOptions
    verified: VerifiedDepths | None


def consistent_points_split(
    views: list[DenseView],
    depths: list[NDArray[np.float32]],
    neighbours: Neighbours,
    options: ReconstructOptions,
    progress: Progress = no_progress,
    verified: VerifiedDepths | None = None,
) -> ConsistentPoints:
    """Fused points that pass the geometric consistency check, their RGB colours and source.

    A pixel's 3D point is kept when its depth in ≥ ``consistency_min_views`` of the view's
    consistency neighbours agrees with their depth maps within ``consistency_rel_tol``
    (relative; ``far_consistency_rel_tol`` for depths beyond ``far_min_depth_m`` when
    ``far_range``); the kept point is the mean of its own and the agreeing back-projections.
    Pixels set in ``verified.masks`` need ≥ ``planar_consistency_min_views`` instead, and
    those at ≥ ``far_min_depth_m`` are taken from every ``planar_far_row_stride``-th row
    (not only every ``point_stride``-th). For them the views of ``verified.checked_by``
    count as well, without entering the mean (their far SGBM depths agree within 3 % and
    would pull an exact plane depth by as much). Where a pixel with a ``verified.fallback``
    depth fails the check, it is tried again at its fallback depth as a verified pixel (a far
    SGBM depth that no neighbour confirms counts as none, where a verified plane depth would
    have filled in). Raises ShapeError for mismatched inputs, DenseReconstructionFailed when
    no point survives.
    """
    _check_consistency_inputs(views, depths, verified)
    ctx = _Consistency(views, depths, neighbours, options, verified)
    chunks: list[ConsistentPoints] = []
    for i in range(len(views)):
        chunks.extend(_view_consistent_points(ctx, i))
        progress("consistency", (i + 1) / len(views))
    if not chunks:
        raise DenseReconstructionFailed(
            "no depth survived the multi-view consistency check; the scene may lack texture "
            "or the photos may not overlap enough"
        )
    return ConsistentPoints(
        np.concatenate([c.points_env for c in chunks]),
        np.concatenate([c.colors_rgb for c in chunks]).astype(np.uint8),
        np.concatenate([c.verified for c in chunks]),
        np.concatenate([c.depth_m for c in chunks]),
    )


def _check_consistency_inputs(
    views: list[DenseView], depths: list[NDArray[np.float32]], verified: VerifiedDepths | None
) -> None:
    if len(views) != len(depths):
        raise ShapeError(f"{len(views)} views but {len(depths)} depth maps")
    if verified is None:
        return
    if [m.shape for m in verified.masks] != [d.shape for d in depths]:
        raise ShapeError("verified masks must match the depth maps one to one")
    fallback = verified.fallback
    if fallback is not None and [m.shape for m in fallback] != [d.shape for d in depths]:
        raise ShapeError("fallback depths must match the depth maps one to one")
    checked_by = verified.checked_by
    if checked_by is not None and len(checked_by) != len(views):
        raise ShapeError(f"{len(views)} views but checked_by for {len(checked_by)}")


def _view_consistent_points(ctx: _Consistency, i: int) -> list[ConsistentPoints]:
    """View i's kept points: its pixels at their own depths, then the pixels that failed at
    their fallback depths (none, one or two non-empty chunks, in that order)."""
    view, depth, options = ctx.views[i], ctx.depths[i], ctx.options
    pts, pix = _view_pixels(ctx, i)
    if len(pts) == 0:
        return []
    own_depth = depth[pix[:, 1], pix[:, 0]]
    src = np.zeros(len(pts), np.bool_)
    if ctx.verified is not None:
        src = ctx.verified.masks[i][pix[:, 1], pix[:, 0]]
    keep, fused = _check_points(ctx, i, pts, own_depth, src, options.far_range)
    out = [_chunk(view, fused, src[keep], own_depth[keep], pix[keep])]
    fallback = None if ctx.verified is None else ctx.verified.fallback
    if fallback is not None:
        alt = fallback[i][pix[:, 1], pix[:, 0]]
        retry = ~keep & (alt > 0) & (own_depth > 0)
        if retry.any():
            # the retried pixel's ray at its fallback depth, as a verified pixel
            centre = view.env_from_cam[:3, 3]
            p_alt = centre + (pts[retry] - centre) * (alt[retry] / own_depth[retry])[:, None]
            ok, fused = _check_points(
                ctx, i, p_alt, alt[retry], np.ones(len(p_alt), np.bool_), True
            )
            out.append(
                _chunk(view, fused, np.ones(len(fused), np.bool_), alt[retry][ok], pix[retry][ok])
            )
    return [c for c in out if len(c.points_env)]


def _view_pixels(ctx: _Consistency, i: int) -> tuple[FloatArray, NDArray[np.int64]]:
    """View i's back-projected (M, 3) env points and (M, 2) pixels (x, y): every
    ``point_stride``-th pixel, plus verified far depths on every ``planar_far_row_stride``-th
    row between them."""
    view, depth, options = ctx.views[i], ctx.depths[i], ctx.options
    pts, pix = backproject(view, depth, options.point_stride)
    rows = options.planar_far_row_stride
    if ctx.verified is not None and rows < options.point_stride:
        # verified far depths (plane depths) also on the rows between the grid's: seen
        # at a grazing angle, a far floor pixel's footprint is 2-5× longer than wide
        far_plane = ctx.verified.masks[i] & (depth >= options.far_min_depth_m)
        cols = options.point_stride
        extra = np.zeros_like(depth)
        extra[::rows, ::cols] = np.where(far_plane, depth, 0.0)[::rows, ::cols]
        extra[::cols, ::cols] = 0.0
        more_pts, more_pix = backproject(view, extra, 1)
        pts, pix = np.concatenate([pts, more_pts]), np.concatenate([pix, more_pix])
    return pts, pix


def _chunk(
    view: DenseView,
    points: FloatArray,
    src: NDArray[np.bool_],
    depth_m: NDArray[np.float32],
    px: NDArray[np.int64],
) -> ConsistentPoints:
    """Kept points with their colours at pixels ``px`` (M, 2) of ``view`` (BGR to RGB)."""
    colors = np.ascontiguousarray(view.image[px[:, 1], px[:, 0]][:, ::-1])
    return ConsistentPoints(points, colors, src, depth_m)


def _check_points(
    ctx: _Consistency,
    i: int,
    points: FloatArray,
    depth_m: NDArray[np.float32],
    verified_px: NDArray[np.bool_],
    far: bool,
) -> tuple[NDArray[np.bool_], FloatArray]:
    """Which of view i's (N, 3) points at own depths ``depth_m`` pass, and the kept ones
    averaged with the agreeing neighbours' measurements; ``far``: the looser tolerance from
    ``far_min_depth_m`` on."""
    options = ctx.options
    rel_tol = np.full(len(points), options.consistency_rel_tol, np.float32)
    if far:
        rel_tol[depth_m >= options.far_min_depth_m] = options.far_consistency_rel_tol
    own = ctx.neighbours.consistency[i]
    support, acc = _agreement(ctx.views, ctx.depths, points, rel_tol, own)
    need = np.where(
        verified_px, options.planar_consistency_min_views, options.consistency_min_views
    ).astype(np.int32)
    lacking = verified_px & (support < need)
    checked = _checked_support(ctx, points, rel_tol, lacking, i)
    keep = support + checked >= need  # checked: agreeing views not in the mean
    return keep, acc[keep] / (1.0 + support[keep, None])


def _checked_support(
    ctx: _Consistency,
    points_env: FloatArray,
    rel_tol: NDArray[np.float32],
    lacking: NDArray[np.bool_],
    i: int,
) -> NDArray[np.int32]:
    """(N,) agreeing views among view ``i``'s ``checked_by`` views (those not already its
    consistency neighbours) for the (N, 3) points flagged in ``lacking``; 0 for the others."""
    out = np.zeros(len(points_env), np.int32)
    checked_by = None if ctx.verified is None else ctx.verified.checked_by
    if checked_by is None or not lacking.any():
        return out
    own = ctx.neighbours.consistency[i]
    extra = tuple(j for j in checked_by[i] if j != i and j not in own)
    if not extra:
        return out
    idx = np.flatnonzero(lacking)
    out[idx], _ = _agreement(ctx.views, ctx.depths, points_env[idx], rel_tol[idx], extra)
    return out
