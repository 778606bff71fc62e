"""Re-projection with visibility: z-buffers by point splatting, visible points, 2D boxes.

A capture's depth as its camera sees it is rendered from the capture's own cloud: each
point is splatted into a z-buffer at reduced resolution (longest side ``max_side`` px) and
the buffer is eroded with a (2·fill+1)² minimum filter so that gaps between splats do not
let hidden points show through. A point is *visible* from a camera when it projects into
the image, in front of the camera, and its depth ≤ z-buffer depth + tolerance, where
``tolerance(d) = tol_m + tol_px · d / f_zbuffer`` (a fixed part plus ``tol_px`` z-buffer
pixels' worth of footprint, for slanted surfaces). Depths in metres along the camera's z.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import minimum_filter

from workers.pipeline.compare.data import Camera
from workers.pipeline.geometry import transform_points

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True, eq=False)
class DepthMap:
    """A camera's z-buffer: ``depth`` (h, w) float32 metres (inf where nothing projects) at
    ``scale`` z-buffer pixels per image pixel."""

    camera: Camera
    depth: NDArray[np.float32]
    scale: float

    @property
    def focal_px(self) -> float:
        """Smallest focal length in z-buffer pixels."""
        return float(min(self.camera.k[0, 0], self.camera.k[1, 1]) * self.scale)


def zbuffer_scale(camera: Camera, max_side: int) -> float:
    """Z-buffer pixels per image pixel so that the longer image side is ≤ ``max_side``."""
    return min(1.0, max_side / max(camera.width, camera.height))


def render_depth(
    camera: Camera, points_env: NDArray[np.float32], max_side: int = 256, fill_px: int = 1
) -> DepthMap:
    """Z-buffer of (N, 3) float32 environment points splatted into ``camera``."""
    scale = zbuffer_scale(camera, max_side)
    w = max(1, round(camera.width * scale))
    h = max(1, round(camera.height * scale))
    cam_from_env = camera.cam_from_env.astype(np.float32)
    p = points_env @ cam_from_env[:3, :3].T + cam_from_env[:3, 3]
    z = p[:, 2]
    front = z > 1e-6
    p, z = p[front], z[front]
    k = camera.k
    inv = np.float32(1.0) / z
    u = p[:, 0] * inv * np.float32(k[0, 0]) + p[:, 1] * inv * np.float32(k[0, 1])
    u += np.float32(k[0, 2])
    v = p[:, 1] * inv * np.float32(k[1, 1]) + np.float32(k[1, 2])
    u *= np.float32(w / camera.width)
    v *= np.float32(h / camera.height)
    ok = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    lin = v[ok].astype(np.int64) * w + u[ok].astype(np.int64)
    buf = np.full(w * h, np.inf, dtype=np.float32)
    np.minimum.at(buf, lin, z[ok])
    depth = buf.reshape(h, w)
    if fill_px > 0:
        depth = minimum_filter(depth, size=2 * fill_px + 1, mode="nearest")
    return DepthMap(camera=camera, depth=depth, scale=scale)


def _lookup(depth_map: DepthMap, uv: FloatArray, inside: BoolArray) -> FloatArray:
    """Z-buffer depth at image pixels ``uv`` (N, 2) where ``inside``; inf elsewhere."""
    h, w = depth_map.depth.shape
    cam = depth_map.camera
    out = np.full(len(uv), np.inf)
    col = np.clip((uv[inside, 0] * (w / cam.width)).astype(np.int64), 0, w - 1)
    row = np.clip((uv[inside, 1] * (h / cam.height)).astype(np.int64), 0, h - 1)
    out[inside] = depth_map.depth[row, col]
    return out


def tolerance(depth_map: DepthMap, z: FloatArray, tol_m: float, tol_px: float) -> FloatArray:
    """Depth tolerance (N,) metres at depths ``z`` (N,) metres."""
    return tol_m + tol_px * np.abs(z) / depth_map.focal_px


def project_in_image(
    camera: Camera, points_env: FloatArray
) -> tuple[FloatArray, FloatArray, BoolArray]:
    """Pixels (N, 2), depths (N,) m and a mask (N,) of (N, 3) points in front and in the image."""
    p_cam = transform_points(camera.cam_from_env, points_env)
    z = p_cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (p_cam[:, :2] / np.where(z > 0, z, np.nan)[:, None]) @ camera.k[:2, :2].T
        uv += camera.k[:2, 2]
        inside = (
            (z > 1e-6)
            & (uv[:, 0] >= 0)
            & (uv[:, 0] < camera.width)
            & (uv[:, 1] >= 0)
            & (uv[:, 1] < camera.height)
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


def seen_empty_counts(
    points_env: FloatArray,
    depth_maps: Sequence[DepthMap],
    tol_m: float = 0.02,
    tol_px: float = 2.0,
) -> NDArray[np.int64]:
    """For (N, 3) points of one capture, how many of the *other* capture's cameras see the
    place as empty: the point projects into the image, in front, and that capture's surface
    at the pixel lies *behind* the point by more than the tolerance. A pixel with no surface
    (inf) or a surface in front (occlusion) is no evidence: the place was not seen.
    """
    counts = np.zeros(len(points_env), dtype=np.int64)
    for dm in depth_maps:
        uv, z, inside = project_in_image(dm.camera, points_env)
        zbuf = _lookup(dm, uv, inside)
        with np.errstate(invalid="ignore"):
            empty = inside & np.isfinite(zbuf) & (zbuf > z + tolerance(dm, z, tol_m, tol_px))
        counts += empty
    return counts


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
    else:
        lo, hi = np.percentile(uv, [percentile, 100.0 - percentile], axis=0)
    return np.array([lo[0], lo[1], hi[0], hi[1]], dtype=np.float64)
