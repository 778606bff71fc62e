"""Re-projection with visibility: z-buffers by point splatting, visible points, 2D boxes.

A capture's depth as its camera sees it is rendered from the capture's own cloud: each
point is splatted into a z-buffer at reduced resolution (longest side ``max_side`` px) and
the buffer is eroded with a (2·fill+1)² minimum filter so that gaps between splats do not
let hidden points show through. A point is *visible* from a camera when it projects into
the image, in front of the camera, and its depth ≤ z-buffer depth + tolerance, where
``tolerance(d) = tol_m + tol_px · d / f_zbuffer`` (a fixed part plus ``tol_px`` z-buffer
pixels' worth of footprint, for slanted surfaces). Depths in metres along the camera's z.

A z-buffer drawn from the fused cloud holds surfaces its camera never saw: where an object
is missing from the cloud, the wall behind it (reconstructed from other views) shows
through. With the camera's photo, :func:`photo_agreement` marks the pixels where the photo
shows the colour of the surface the z-buffer holds; only there does the camera's view of
"empty space in front of that surface" count (:func:`depth_votes`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import minimum_filter

from workers.pipeline.compare.data import Camera
from workers.pipeline.errors import ShapeError
from workers.pipeline.geometry import as_points

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True, eq=False)
class DepthMap:
    """A camera's z-buffer: ``depth`` (h, w) float32 metres (inf where nothing projects) at
    ``scale`` z-buffer pixels per image pixel; ``photo_agrees`` (h, w) bool, where the
    camera's photo shows the surface the z-buffer holds (None: no photo, every pixel
    counts)."""

    camera: Camera
    depth: NDArray[np.float32]
    scale: float
    photo_agrees: NDArray[np.bool_] | None = None

    @property
    def focal_px(self) -> float:
        """Smallest focal length in z-buffer pixels."""
        return float(min(self.camera.k[0, 0], self.camera.k[1, 1]) * self.scale)


def zbuffer_scale(camera: Camera, max_side: int) -> float:
    """Z-buffer pixels per image pixel so that the longer image side is ≤ ``max_side``."""
    return min(1.0, max_side / max(camera.width, camera.height))


def camera_coords(
    cam_from_env: FloatArray, x: NDArray[Any], y: NDArray[Any], z: NDArray[Any]
) -> tuple[NDArray[Any], NDArray[Any], NDArray[Any]]:
    """Camera coordinates of points given as columns (each (N,)), elementwise;
    ``cam_from_env`` (≥ 3, 4), or (3, 4, N): a camera per point.

    Deliberately not ``points @ R.T``: a (N, 3) × (3, 3) product goes to multithreaded BLAS,
    which on a shared, oversubscribed machine was 10× slower than these 9 fused
    multiply-adds per point.
    """
    m = cam_from_env.astype(x.dtype, copy=False)
    xc = x * m[0, 0] + y * m[0, 1] + z * m[0, 2] + m[0, 3]
    yc = x * m[1, 0] + y * m[1, 1] + z * m[1, 2] + m[1, 3]
    zc = x * m[2, 0] + y * m[2, 1] + z * m[2, 2] + m[2, 3]
    return xc, yc, zc


def _splat(
    camera: Camera, cols: NDArray[np.float32], scale: float
) -> tuple[NDArray[np.int64], NDArray[np.float32], NDArray[np.int64], int, int]:
    """Z-buffer pixel (linear index), depth and source index of each (3, N) column point
    that projects in front of ``camera`` into its image; and the buffer's width, height."""
    w = max(1, round(camera.width * scale))
    h = max(1, round(camera.height * scale))
    xc, yc, zc = camera_coords(camera.cam_from_env, cols[0], cols[1], cols[2])
    front = np.flatnonzero(zc > 1e-6)
    xc, yc, zc = xc[front], yc[front], zc[front]
    k = camera.k
    sx, sy = w / camera.width, h / camera.height
    inv = np.float32(1.0) / zc
    xn, yn = xc * inv, yc * inv
    u = xn * np.float32(k[0, 0] * sx) + yn * np.float32(k[0, 1] * sx) + np.float32(k[0, 2] * sx)
    v = yn * np.float32(k[1, 1] * sy) + np.float32(k[1, 2] * sy)
    ok = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    lin = v[ok].astype(np.int64) * w + u[ok].astype(np.int64)
    return lin, zc[ok], front[ok], w, h


def _surface_index(
    lin: NDArray[np.int64],
    z: NDArray[np.float32],
    source: NDArray[np.int64],
    raw: NDArray[np.float32],
    depth: NDArray[np.float32],
    fill_px: int,
) -> NDArray[np.int64]:
    """(h, w) index of the point whose surface each pixel of the filled z-buffer ``depth``
    holds: the point that won the pixel in the ``raw`` buffer, or where the minimum filter
    took a neighbour's depth (within ``fill_px``), that neighbour's; −1 where none."""
    h, w = depth.shape
    own = np.full(h * w, -1, dtype=np.int64)
    won = z <= raw.reshape(-1)[lin]
    own[lin[won]] = source[won]
    out = np.where(raw.reshape(-1) == depth.reshape(-1), own, -1)
    todo = np.flatnonzero((out < 0) & np.isfinite(depth.reshape(-1)))
    rows, cols = np.divmod(todo, w)
    for dy in range(-fill_px, fill_px + 1):
        for dx in range(-fill_px, fill_px + 1):
            r, c = np.clip(rows + dy, 0, h - 1), np.clip(cols + dx, 0, w - 1)
            take = (out[todo] < 0) & (raw[r, c] == depth.reshape(-1)[todo])
            out[todo[take]] = own[r[take] * w + c[take]]
    return out.reshape(h, w)


def render_depth(
    camera: Camera,
    points_env: NDArray[np.float32],
    max_side: int = 256,
    fill_px: int = 1,
    colors: NDArray[np.float32] | None = None,
    photo: NDArray[np.float32] | None = None,
    colour_tolerance: float = 0.1,
) -> DepthMap:
    """Z-buffer of (N, 3) environment points splatted into ``camera`` (float32 maths).

    ``points_env`` may also be given as a (3, N) C-contiguous array of columns (faster).
    With the points' (N, 3) ``colors`` and the camera's ``photo`` (H, W, 3), both RGB in
    [0, 1] (the photo at any size, resized to the buffer's grid), the map gets
    ``photo_agrees`` (:func:`photo_agreement` within ``colour_tolerance``).
    """
    cols = points_env if points_env.shape[0] == 3 and points_env.ndim == 2 else points_env.T
    if len(cols) != 3:
        raise ShapeError(f"points_env must be (N, 3) or (3, N), got {points_env.shape}")
    cols = np.ascontiguousarray(cols, dtype=np.float32)
    scale = zbuffer_scale(camera, max_side)
    lin, z, source, w, h = _splat(camera, cols, scale)
    buf = np.full(w * h, np.inf, dtype=np.float32)
    np.minimum.at(buf, lin, z)
    raw = buf.reshape(h, w)
    depth = minimum_filter(raw, size=2 * fill_px + 1, mode="nearest") if fill_px > 0 else raw
    agrees = None
    if colors is not None and photo is not None:
        index = _surface_index(lin, z, source, raw, depth, fill_px)
        small = np.asarray(cv2.resize(photo, (w, h), interpolation=cv2.INTER_AREA), np.float32)
        agrees = photo_agreement(index, colors, small, colour_tolerance)
    return DepthMap(camera=camera, depth=depth, scale=scale, photo_agrees=agrees)


def photo_agreement(
    surface_index: NDArray[np.int64],
    colors: NDArray[np.float32],
    photo_rgb: NDArray[np.float32],
    tolerance: float,
) -> NDArray[np.bool_]:
    """(h, w) pixels where the camera's photo (h, w, 3, RGB in [0, 1], on the z-buffer's
    grid) shows the colour of the surface the z-buffer holds (``surface_index`` (h, w) into
    the (N, 3) ``colors``, −1 where none): every channel within ``tolerance`` once the
    photo's gain per channel is matched to the cloud's (the median ratio over a sample of
    the pixels with a surface: exposure and white balance differ from photo to photo, the
    cloud's colours are averages). Pixels without a surface agree (nothing to contradict)."""
    has = surface_index >= 0
    surface, photo = colors[surface_index[has]], photo_rgb[has]
    sample = slice(None, None, 4)
    bright = (photo[sample] > 0.02).all(axis=1)
    gain = np.ones(3, dtype=np.float32)
    if np.count_nonzero(bright) >= 100:
        gain = np.median(surface[sample][bright] / photo[sample][bright], axis=0)
    agrees = np.ones(surface_index.shape, dtype=bool)
    agrees[has] = np.abs(photo * gain.astype(np.float32) - surface).max(axis=1) <= tolerance
    return agrees


def _pixels(depth_map: DepthMap, uv: FloatArray) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Z-buffer rows and columns of image pixels ``uv`` (N, 2) (clipped to the buffer)."""
    h, w = depth_map.depth.shape
    cam = depth_map.camera
    col = np.clip((uv[:, 0] * (w / cam.width)).astype(np.int64), 0, w - 1)
    row = np.clip((uv[:, 1] * (h / cam.height)).astype(np.int64), 0, h - 1)
    return row, col


def depth_at(depth_map: DepthMap, uv: FloatArray) -> NDArray[np.float32]:
    """Z-buffer depth (metres, inf where nothing projects) at image pixels ``uv`` (N, 2)
    inside the image."""
    row, col = _pixels(depth_map, uv)
    out: NDArray[np.float32] = depth_map.depth[row, col]
    return out


def _lookup(depth_map: DepthMap, uv: FloatArray, inside: BoolArray) -> FloatArray:
    """Z-buffer depth at image pixels ``uv`` (N, 2) where ``inside``; inf elsewhere."""
    out = np.full(len(uv), np.inf)
    out[inside] = depth_at(depth_map, uv[inside])
    return out


def tolerance(depth_map: DepthMap, z: FloatArray, tol_m: float, tol_px: float) -> FloatArray:
    """Depth tolerance (N,) metres at depths ``z`` (N,) metres."""
    return tol_m + tol_px * np.abs(z) / depth_map.focal_px


def project_in_image(
    camera: Camera, points_env: FloatArray
) -> tuple[FloatArray, FloatArray, BoolArray]:
    """Pixels (N, 2), depths (N,) m and a mask (N,) of (N, 3) points in front and in the image."""
    pts = as_points(points_env, "points_env")
    return project_points(camera.k, camera.cam_from_env, camera.width, camera.height, pts)


def project_points(
    k: NDArray[Any], cam_from_env: NDArray[Any], width: Any, height: Any, points_env: FloatArray
) -> tuple[FloatArray, FloatArray, BoolArray]:
    """:func:`project_in_image` of (N, 3) points through one camera (``k`` (3, 3),
    ``cam_from_env`` (4, 4), ``width``/``height`` pixels) or through a camera per point,
    stacked along a last axis (``k`` (3, 3, N), ``cam_from_env`` (3, 4, N), (N,) sizes)."""
    xc, yc, z = camera_coords(cam_from_env, points_env[:, 0], points_env[:, 1], points_env[:, 2])
    with np.errstate(divide="ignore", invalid="ignore"):
        zs = np.where(z > 0, z, np.nan)
        xn, yn = xc / zs, yc / zs
        uv = np.column_stack([k[0, 0] * xn + k[0, 1] * yn + k[0, 2], k[1, 1] * yn + k[1, 2]])
        inside = (
            (z > 1e-6)
            & (uv[:, 0] >= 0)
            & (uv[:, 0] < width)
            & (uv[:, 1] >= 0)
            & (uv[:, 1] < height)
        )
    return uv, z, inside


def visible_points(
    camera: Camera,
    points_env: FloatArray,
    depth_map: DepthMap | None,
    tol_m: float = 0.02,
    tol_px: float = 2.0,
) -> tuple[FloatArray, BoolArray]:
    """Pixels (N, 2) and visibility mask (N,) of (N, 3) points seen by ``camera``.

    Without a ``depth_map`` occlusion is ignored (the thesis's method): visible = in image.
    """
    uv, z, inside = project_in_image(camera, points_env)
    if depth_map is None:
        return uv, inside
    zbuf = _lookup(depth_map, uv, inside)
    with np.errstate(invalid="ignore"):
        vis = inside & (z <= zbuf + tolerance(depth_map, z, tol_m, tol_px))
    return uv, vis


def seen_by_any(
    points_env: FloatArray,
    normals_env: FloatArray,
    depth_maps: Sequence[DepthMap],
    tol_m: float = 0.005,
    tol_px: float = 2.0,
) -> BoolArray:
    """(N,) mask of the (N, 3) surface points (unit outward ``normals_env`` (N, 3)) that
    some camera of ``depth_maps`` sees: in its image, facing it and not behind its
    z-buffer by more than the tolerance."""
    seen = np.zeros(len(points_env), dtype=bool)
    for dm in depth_maps:
        m = dm.camera.cam_from_env
        centre = -m[:3, :3].T @ m[:3, 3]
        uv, z, inside = project_in_image(dm.camera, points_env)
        inside &= np.einsum("ij,ij->i", centre - points_env, normals_env) > 0.0
        zbuf = _lookup(dm, uv, inside)
        with np.errstate(invalid="ignore"):
            seen |= inside & (z <= zbuf + tolerance(dm, z, tol_m, tol_px))
    return seen


def depth_votes(
    points_env: FloatArray,
    depth_maps: Sequence[DepthMap],
    tol_m: float = 0.02,
    tol_px: float = 2.0,
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """For (N, 3) points, how many cameras of ``depth_maps`` see each place *empty* (the
    point projects into the image, in front, and the surface at its pixel lies behind it
    by more than the tolerance, and the camera's photo shows that surface where the map
    has ``photo_agrees``) and how many see a surface *there* (within the tolerance). A
    pixel with no surface (inf) or a surface in front (occlusion) is no evidence either
    way, nor is a surface behind that the photo does not show (the cloud misses what
    stands in front of it there)."""
    empty = np.zeros(len(points_env), dtype=np.int64)
    there = np.zeros(len(points_env), dtype=np.int64)
    for dm in depth_maps:
        uv, z, inside = project_in_image(dm.camera, points_env)
        zbuf = _lookup(dm, uv, inside)
        tol = tolerance(dm, z, tol_m, tol_px)
        with np.errstate(invalid="ignore"):
            seen = inside & np.isfinite(zbuf)
            behind = seen & (zbuf > z + tol)
            there += seen & (np.abs(zbuf - z) <= tol)
        if dm.photo_agrees is not None and behind.any():
            rows, cols = _pixels(dm, uv[behind])
            behind[np.flatnonzero(behind)] = dm.photo_agrees[rows, cols]
        empty += behind
    return empty, there


def covered_mask(
    points_env: FloatArray,
    depth_maps: Sequence[DepthMap],
    tol_m: float = 0.02,
    tol_px: float = 2.0,
) -> BoolArray:
    """Which (N, 3) points of one capture lie where the *other* capture looked: some camera
    of it projects the point into its image, in front, and its surface at that pixel is not
    in front of the point by more than the tolerance (it saw the place, full or empty).
    Points elsewhere cannot be compared fairly and are left out of distance statistics.
    """
    covered = np.zeros(len(points_env), dtype=bool)
    for dm in depth_maps:
        todo = ~covered
        uv, z, inside = project_in_image(dm.camera, points_env[todo])
        zbuf = _lookup(dm, uv, inside)
        with np.errstate(invalid="ignore"):
            ok = inside & np.isfinite(zbuf) & (zbuf >= z - tolerance(dm, z, tol_m, tol_px))
        covered[np.flatnonzero(todo)[ok]] = True
    return covered


def box_from_pixels(uv: FloatArray, percentile: float = 2.0) -> FloatArray:
    """Robust 2D box ``[x1, y1, x2, y2]`` pixels of (N ≥ 1, 2) pixels: the ``percentile``
    and ``100 − percentile`` percentiles of x and y (0 gives the full extent)."""
    if percentile <= 0:
        lo, hi = uv.min(axis=0), uv.max(axis=0)
        return np.array([lo[0], lo[1], hi[0], hi[1]], dtype=np.float64)
    # np.percentile's linear interpolation by partial sorting (np.percentile's own overhead
    # dominated for the thousands of small boxes of a comparison)
    n = len(uv)
    pos = np.array([percentile, 100.0 - percentile]) * ((n - 1) / 100.0)
    below = np.floor(pos).astype(np.int64)
    above = np.minimum(below + 1, n - 1)
    part = np.partition(uv, np.unique(np.concatenate([below, above])), axis=0)
    q = part[below] + (part[above] - part[below]) * (pos - below)[:, None]
    return np.array([q[0, 0], q[0, 1], q[1, 0], q[1, 1]], dtype=np.float64)
