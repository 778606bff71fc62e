"""CPU multi-view stereo: neighbour selection, rectified SGBM per pair, per-view depth maps,
and a geometric consistency filter across views.

Everything is in the env frame, metres, OpenCV camera axes. Images are undistorted and
scaled by ``options.mvs_scale`` first; depth maps live on that scaled pinhole grid.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

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
    """Per view: stereo partners (indices) and consistency neighbours (indices)."""

    stereo: tuple[tuple[int, ...], ...]
    consistency: tuple[tuple[int, ...], ...]


def load_dense_views(
    images_dir: Path, views: tuple[CameraView, ...], scale: float
) -> list[DenseView]:
    """Read, undistort and rescale every view's image; K follows (pixel centres kept)."""
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
        if scale != 1.0:
            w, h = round(img.shape[1] * scale), round(img.shape[0] * scale)
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
    (saturating at 15°). Consistency neighbours are the views sharing the most points.
    """
    n = len(views)
    if visibility.shape != (len(points_env), n):
        raise ShapeError(f"visibility must be ({len(points_env)}, {n}), got {visibility.shape}")
    centres = np.stack([v.env_from_cam[:3, 3] for v in views])
    axes = np.stack([_axis(v) for v in views])
    vis = visibility.astype(np.float32)
    shared = vis.T @ vis
    stereo: list[tuple[int, ...]] = []
    consist: list[tuple[int, ...]] = []
    for i in range(n):
        scores: list[tuple[float, int]] = []
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
            scores.append((float(shared[i, j]) * weight, j))
        scores.sort(reverse=True)
        stereo.append(tuple(j for _, j in scores[: options.pairs_per_view]))
        order = [int(j) for j in np.argsort(-shared[i]) if j != i and shared[i, j] >= 10]
        consist.append(tuple(order[: options.consistency_views]))
    return Neighbours(tuple(stereo), tuple(consist))


def _ceil16(v: float) -> int:
    return int(np.ceil(v / 16.0) * 16)


def pair_depth(
    ref: DenseView,
    src: DenseView,
    points_env: FloatArray,
    options: ReconstructOptions,
) -> NDArray[np.float32]:
    """Depth map (H, W) float32 of ``ref`` in metres (0 = unknown) from SGBM on the rectified
    pair (ref, src). ``points_env`` (N, 3) sparse points seen by both give the disparity range.
    """
    w, h = ref.size
    src_from_ref = src.cam_from_env @ ref.env_from_cam
    rot = np.ascontiguousarray(src_from_ref[:3, :3])
    trans = np.ascontiguousarray(src_from_ref[:3, 3].reshape(3, 1))
    if src.size != ref.size:
        raise ShapeError("stereo pairs must share an image size at MVS scale")
    r1, r2, p1, p2, _, _, _ = cv2.stereoRectify(
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
    vertical = abs(p2[1, 3]) > abs(p2[0, 3])
    tx = p2[1, 3] if vertical else p2[0, 3]
    flip = tx > 0  # src lies left (or above) of ref in the rectified frame
    f = float(p1[0, 0])
    baseline = abs(float(tx)) / f
    cx, cy = float(p1[0, 2]), float(p1[1, 2])

    # disparity range from the sparse points in the rectified ref frame
    p_cam = points_env @ ref.cam_from_env[:3, :3].T + ref.cam_from_env[:3, 3]
    z_rect = (p_cam @ r1.T)[:, 2]
    z_rect = z_rect[z_rect > 1e-6]
    if len(z_rect) < 5:
        return np.zeros((h, w), np.float32)
    d = f * baseline / z_rect
    dmin = max(0.0, float(np.percentile(d, 1)) * 0.85 - 2.0)
    dmax = float(np.percentile(d, 99)) * 1.15 + 2.0
    min_disp = int(np.floor(dmin))
    num = max(16, _ceil16(dmax - min_disp))
    if num > options.max_disparities:
        log.info("pair %s-%s: disparity range %d capped", ref.name, src.name, num)
        num = options.max_disparities

    def canon(img: NDArray[np.uint8]) -> NDArray[np.uint8]:
        out = img.T if vertical else img
        return np.ascontiguousarray(out[:, ::-1] if flip else out)

    gray = [cv2.cvtColor(v.image, cv2.COLOR_BGR2GRAY) for v in (ref, src)]
    maps = [
        cv2.initUndistortRectifyMap(v.k_matrix, np.zeros(5), r, p, (w, h), cv2.CV_32FC1)
        for v, r, p in ((ref, r1, p1), (src, r2, p2))
    ]
    rect = [
        canon(np.asarray(cv2.remap(g, m[0], m[1], cv2.INTER_LINEAR), np.uint8))
        for g, m in zip(gray, maps, strict=True)
    ]
    valid_src = canon(
        np.asarray(
            cv2.remap(np.full((h, w), 255, np.uint8), maps[0][0], maps[0][1], cv2.INTER_NEAREST),
            np.uint8,
        )
    )
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
    disp = sgbm.compute(rect[0], rect[1]).astype(np.float32) / 16.0
    disp[(disp <= max(min_disp, 0) + 0.5) | (valid_src == 0)] = np.nan
    if flip:
        disp = disp[:, ::-1]
    if vertical:
        disp = disp.T
    disp = np.ascontiguousarray(disp)

    # sample the rectified disparity at every ref pixel
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pix = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
    rect_pix = cv2.undistortPoints(pix, ref.k_matrix, np.zeros(5), R=r1, P=p1).reshape(h, w, 2)
    sampled = cv2.remap(
        disp,
        rect_pix[..., 0].astype(np.float32),
        rect_pix[..., 1].astype(np.float32),
        cv2.INTER_NEAREST,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=float("nan"),
    )
    with np.errstate(divide="ignore", invalid="ignore"):
        zr = f * baseline / sampled
        x_rect = np.stack(
            [(rect_pix[..., 0] - cx) * zr / f, (rect_pix[..., 1] - cy) * zr / f, zr], axis=-1
        )
        depth = (x_rect @ r1)[..., 2]  # (R1ᵀ x)_z, row-vector form
    depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0)
    return depth.astype(np.float32)


def compute_depth_maps(
    views: list[DenseView],
    neighbours: Neighbours,
    points_env: FloatArray,
    visibility: NDArray[np.bool_],
    options: ReconstructOptions,
    progress: Progress = no_progress,
) -> list[NDArray[np.float32]]:
    """One (H, W) float32 depth map per view (metres, 0 = unknown) from its stereo partners;
    with several partners, the per-pixel median of the valid estimates."""
    out = []
    for i, view in enumerate(views):
        estimates = []
        for j in neighbours.stereo[i]:
            mask = visibility[:, i] & visibility[:, j]
            estimates.append(pair_depth(view, views[j], points_env[mask], options))
        if not estimates:
            out.append(np.zeros(view.image.shape[:2], np.float32))
        elif len(estimates) == 1:
            out.append(estimates[0])
        else:
            stack = np.stack(estimates)
            stack[stack <= 0] = np.nan
            with np.errstate(all="ignore"):
                med = np.nanmedian(stack, axis=0)
            out.append(np.nan_to_num(med, nan=0.0).astype(np.float32))
        progress("stereo", (i + 1) / len(views))
    return out


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
    view: DenseView, depth: NDArray[np.float32], points_env: FloatArray
) -> tuple[FloatArray, FloatArray, NDArray[np.int64], NDArray[np.int64]]:
    """Project points into ``view``: (their depth, the map's depth there, px x, px y)."""
    p_cam = points_env @ view.cam_from_env[:3, :3].T + view.cam_from_env[:3, 3]
    z = p_cam[:, 2]
    k = view.k_matrix
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.rint(k[0, 0] * p_cam[:, 0] / z + k[0, 2])
        v = np.rint(k[1, 1] * p_cam[:, 1] / z + k[1, 2])
    h, w = depth.shape
    inside = (z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    ui = np.where(inside, u, 0).astype(np.int64)
    vi = np.where(inside, v, 0).astype(np.int64)
    d = np.where(inside, depth[vi, ui], 0.0).astype(np.float64)
    return z, d, ui, vi


def consistent_points(
    views: list[DenseView],
    depths: list[NDArray[np.float32]],
    neighbours: Neighbours,
    options: ReconstructOptions,
    progress: Progress = no_progress,
) -> tuple[FloatArray, NDArray[np.uint8]]:
    """Fused points that pass the geometric consistency check, and their RGB colours.

    A pixel's 3D point is kept when its depth in ≥ ``consistency_min_views`` of the view's
    consistency neighbours agrees with their depth maps within ``consistency_rel_tol``
    (relative); the kept point is the mean of its own and the agreeing back-projections.
    Returns ((M, 3) env-frame metres, (M, 3) uint8 RGB).
    """
    if len(views) != len(depths):
        raise ShapeError(f"{len(views)} views but {len(depths)} depth maps")
    all_pts: list[FloatArray] = []
    all_cols: list[NDArray[np.uint8]] = []
    tol = options.consistency_rel_tol
    for i, view in enumerate(views):
        pts, pix = backproject(view, depths[i], options.point_stride)
        if len(pts) == 0:
            continue
        support = np.zeros(len(pts), np.int32)
        acc = pts.copy()
        for j in neighbours.consistency[i]:
            z, d, _, _ = _sample_depth(views[j], depths[j], pts)
            ok = (d > 0) & (np.abs(d - z) <= tol * z)
            if not ok.any():
                continue
            support += ok
            # back-project the neighbour's own measurement along the same ray of view j
            scale = np.where(ok, d / np.where(z > 0, z, 1.0), 0.0)
            p_cam_j = pts @ views[j].cam_from_env[:3, :3].T + views[j].cam_from_env[:3, 3]
            q_env = (p_cam_j * scale[:, None]) @ views[j].env_from_cam[:3, :3].T + views[
                j
            ].env_from_cam[:3, 3]
            acc[ok] += q_env[ok]
        keep = support >= options.consistency_min_views
        if keep.any():
            all_pts.append(acc[keep] / (1.0 + support[keep, None]))
            bgr = view.image[pix[keep, 1], pix[keep, 0]]
            all_cols.append(np.ascontiguousarray(bgr[:, ::-1]))
        progress("consistency", (i + 1) / len(views))
    if not all_pts:
        raise DenseReconstructionFailed(
            "no depth survived the multi-view consistency check; the scene may lack texture "
            "or the photos may not overlap enough"
        )
    return np.concatenate(all_pts), np.concatenate(all_cols).astype(np.uint8)
