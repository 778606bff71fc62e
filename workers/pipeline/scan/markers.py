"""The environment's marker sheet found in a coloured scan: its frame.

Steps: the largest planes of the cloud (Open3D RANSAC on a thinned copy, then a
least-squares fit to the full-density points within ``plane_distance_m``) → each plane's
coloured points drawn as a grey raster at ``raster_m`` per pixel (bilinear splats,
normalised so gaps between points fill in) → ArUco detection of the sheet's dictionary in
that raster, from both sides of the plane (the printed face may face either way) → the
detected corners back to 3D on the plane → a rigid fit (Kabsch, no scale) of those corners,
``scan`` frame, to the sheet's known corners, ``env`` frame.

Corners follow the contract: a marker's corners sit at (−s/2, s/2, 0), (s/2, s/2, 0),
(s/2, −s/2, 0), (−s/2, −s/2, 0) in its frame, in the order OpenCV detects them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from workers.pipeline.errors import ReconstructionError, ShapeError
from workers.pipeline.geometry import Mat4, as_points, transform_points
from workers.pipeline.reconstruct.markers import MarkerReference, detect_markers
from workers.pipeline.scan.options import ScanOptions
from workers.pipeline.seeded import seeded_open3d

FloatArray = NDArray[np.float64]
ColorArray = NDArray[np.uint8]


class NoUsableFrame(ReconstructionError):
    """The scan's frame was to come from the marker sheet, and it was not found."""

    code = "NoUsableFrame"


@dataclass(frozen=True)
class SheetFit:
    """The frame found: ``env_from_scan`` (4×4 rigid, metres), the RMS corner distance
    after the fit ``residual_m``, each used marker's RMS, and how many planes were searched."""

    env_from_scan: Mat4
    residual_m: float
    per_marker_m: dict[int, float]
    used: tuple[int, ...]
    planes_searched: int
    corners_scan: dict[int, FloatArray]  # id → (4, 3) detected corners, scan frame

    def centres_scan(self) -> FloatArray:
        """(M, 3) centres of the used markers in the scan frame, metres."""
        return np.asarray([self.corners_scan[i].mean(axis=0) for i in self.used])


def kabsch(src_points: FloatArray, dst_points: FloatArray) -> Mat4:
    """Least-squares rigid ``dst_from_src`` (rotation and translation, no scale) of matching
    (N ≥ 3, 3) points, not collinear. Raises ShapeError otherwise."""
    src, dst = as_points(src_points, "src_points"), as_points(dst_points, "dst_points")
    if src.shape != dst.shape or len(src) < 3:
        raise ShapeError(f"need matching (N≥3, 3) arrays, got {src.shape} and {dst.shape}")
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    u, d, vt = np.linalg.svd((dst - mu_d).T @ (src - mu_s))
    if d[1] <= 1e-12 * max(d[0], 1e-300):
        raise ShapeError("points are collinear; the rigid transform is not determined")
    sign = np.diag([1.0, 1.0, np.sign(np.linalg.det(u) * np.linalg.det(vt)) or 1.0])
    out = np.eye(4)
    out[:3, :3] = u @ sign @ vt
    out[:3, 3] = mu_d - out[:3, :3] @ mu_s
    return out


@dataclass(frozen=True)
class _Plane:
    origin: FloatArray  # (3,) a point on the plane, scan frame
    u: FloatArray  # (3,) unit, in the plane
    v: FloatArray  # (3,) unit, in the plane, u × v = normal
    index: NDArray[np.int64]  # the full-density points within the slab


def _planes(points: FloatArray, options: ScanOptions) -> list[_Plane]:
    """The ``max_planes`` largest planes, each refit to the full-density points near it."""
    thin = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    thin = thin.voxel_down_sample(options.plane_voxel_m)
    left = np.asarray(thin.points)
    out: list[_Plane] = []
    with seeded_open3d(options.seed):  # one draw sequence for all the planes
        for _ in range(options.max_planes):
            if len(left) < options.plane_min_points:
                break
            cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(left))
            model, inliers = cloud.segment_plane(
                options.plane_distance_m, 3, options.plane_iterations
            )
            if len(inliers) < options.plane_min_points:
                break
            left = np.delete(left, inliers, axis=0)
            normal = np.asarray(model[:3], np.float64)
            offset = float(model[3]) / float(np.linalg.norm(normal))
            normal /= np.linalg.norm(normal)
            near = np.flatnonzero(np.abs(points @ normal + offset) < options.plane_distance_m)
            if len(near) < 3:
                continue
            centre = points[near].mean(axis=0)
            _, _, vt = np.linalg.svd(points[near] - centre, full_matrices=False)
            normal = vt[2]
            near = near[np.abs((points[near] - centre) @ normal) < options.plane_distance_m / 2]
            if len(near) < options.plane_min_points:
                continue
            u = vt[0] / np.linalg.norm(vt[0])
            v = np.cross(normal, u)
            out.append(_Plane(centre, u, v, near))
    return out


def _raster(
    uv: FloatArray, grey: FloatArray, pixel_m: float
) -> tuple[NDArray[np.uint8], FloatArray]:
    """Grey image of points at plane coordinates ``uv`` (N, 2) metres: column = u, row =
    −v (v up), pixel centres at ``origin + (col, −row) × pixel_m``. Returns the 8-bit image
    and the (2,) plane coordinates of pixel (0, 0)."""
    origin = np.asarray([uv[:, 0].min(), uv[:, 1].max()])
    col = (uv[:, 0] - origin[0]) / pixel_m
    row = (origin[1] - uv[:, 1]) / pixel_m
    h, w = int(row.max()) + 2, int(col.max()) + 2
    c0, r0 = np.floor(col).astype(np.int64), np.floor(row).astype(np.int64)
    fc, fr = col - c0, row - r0
    acc = np.zeros(h * w)
    weight = np.zeros(h * w)
    for dr, dc, wgt in (
        (0, 0, (1 - fr) * (1 - fc)), (0, 1, (1 - fr) * fc), (1, 0, fr * (1 - fc)), (1, 1, fr * fc)
    ):  # fmt: skip
        flat = (r0 + dr) * w + (c0 + dc)
        acc += np.bincount(flat, weights=wgt * grey, minlength=h * w)
        weight += np.bincount(flat, weights=wgt, minlength=h * w)
    acc_img = cv2.GaussianBlur(acc.reshape(h, w), (0, 0), 1.0)
    w_img = cv2.GaussianBlur(weight.reshape(h, w), (0, 0), 1.0)
    img = np.where(w_img > 1e-3, acc_img / np.maximum(w_img, 1e-12), 128.0)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), origin


def _spacing_m(u: FloatArray, v: FloatArray, cell_m: float = 0.02) -> float:
    """Mean spacing of points at plane coordinates (u, v) metres: √(covered area / count),
    the area being the occupied ``cell_m`` cells."""
    cells = np.unique(np.floor(np.column_stack([u, v]) / cell_m).astype(np.int64), axis=0)
    return float(np.sqrt(len(cells) * cell_m**2 / max(len(u), 1)))


def _detect_in_tiles(
    uv: FloatArray, grey: FloatArray, dictionary: str, options: ScanOptions, overlap_m: float
) -> dict[int, FloatArray]:
    """ArUco corners (id → (4, 2) plane coordinates, metres) of points at ``uv`` (N, 2)
    with their ``grey`` levels, rasterised and searched one tile of at most
    ``raster_tile_px`` pixels a side at a time (tiles overlap by ``overlap_m``), so a
    large plane never becomes one huge image."""
    found: dict[int, FloatArray] = {}
    step = options.raster_tile_px * options.raster_m - overlap_m
    lo, hi = uv.min(axis=0), uv.max(axis=0)
    for u0 in np.arange(lo[0], max(hi[0] - overlap_m, lo[0]) + 1e-9, step):
        in_u = np.flatnonzero((uv[:, 0] >= u0) & (uv[:, 0] < u0 + step + overlap_m))
        for v0 in np.arange(lo[1], max(hi[1] - overlap_m, lo[1]) + 1e-9, step):
            tile = in_u[(uv[in_u, 1] >= v0) & (uv[in_u, 1] < v0 + step + overlap_m)]
            if len(tile) < 3:
                continue
            img, origin = _raster(uv[tile], grey[tile], options.raster_m)
            for marker_id, px in detect_markers(img, dictionary).items():
                at = np.column_stack(
                    [
                        origin[0] + px[:, 0] * options.raster_m,
                        origin[1] - px[:, 1] * options.raster_m,
                    ]
                )
                found.setdefault(marker_id, at)
    return found


def _corners_on_plane(
    points: FloatArray,
    grey: FloatArray,
    plane: _Plane,
    reference: MarkerReference,
    options: ScanOptions,
) -> dict[int, FloatArray]:
    """Reference markers found on one plane: id → (4, 3) corners in the scan frame. The
    other face is tried when the first shows none."""
    best: dict[int, FloatArray] = {}
    local = points[plane.index] - plane.origin
    if _spacing_m(local @ plane.u, local @ plane.v) > options.max_point_spacing_m:
        return best  # too sparse to show a marker's cells
    for side in (1.0, -1.0):
        v = side * plane.v  # flipping v flips the normal: the other face
        uv = np.column_stack([local @ plane.u, local @ v])
        found = _detect_in_tiles(
            uv, grey[plane.index], reference.dictionary, options, 2.0 * reference.size_m
        )
        corners = {
            marker_id: plane.origin + np.outer(at[:, 0], plane.u) + np.outer(at[:, 1], v)
            for marker_id, at in found.items()
            if marker_id in reference.poses
        }
        if len(corners) > len(best):
            best = corners
        if best:  # a mirrored print decodes to no marker, or rarely a wrong one
            break
    return best


def find_sheet(
    points_scan: FloatArray,
    colors: ColorArray,
    reference: MarkerReference,
    options: ScanOptions,
    progress: Callable[[float], None] | None = None,
) -> SheetFit:
    """``env_from_scan`` from the marker sheet seen in a coloured scan.

    ``points_scan`` (N, 3) metres, ``colors`` (N, 3) uint8 RGB (or grey from intensity).
    A marker whose corners fit worse than ``max_marker_residual_m`` is dropped and the fit
    redone. ``progress`` gets the share of planes searched (0..1) after each plane. Raises
    NoUsableFrame when no marker of the sheet is found.
    """
    pts = as_points(points_scan, "points_scan")
    if np.shape(colors) != pts.shape:
        raise ShapeError(f"colors must be {pts.shape}, got {np.shape(colors)}")
    grey = np.asarray(colors, np.float64) @ np.asarray([0.299, 0.587, 0.114])
    planes = _planes(pts, options)
    found: dict[int, FloatArray] = {}
    for k, plane in enumerate(planes):
        for marker_id, corners in _corners_on_plane(pts, grey, plane, reference, options).items():
            found.setdefault(marker_id, corners)
        if progress is not None:
            progress((k + 1) / len(planes))
    if not found:
        raise NoUsableFrame(
            f"markers asked for, but none of the environment's {reference.dictionary} markers "
            f"{sorted(reference.poses)} was found in the scan ({len(planes)} planes searched); "
            "the sheet must be in the scan with its print in colour or intensity, or give a "
            "transform"
        )
    used = sorted(found)
    for _ in range(2):
        env_from_scan = kabsch(
            np.concatenate([found[i] for i in used]),
            np.concatenate([reference.corners_env(i) for i in used]),
        )
        per_marker = {
            i: float(np.sqrt(np.mean(np.sum(
                (transform_points(env_from_scan, found[i]) - reference.corners_env(i)) ** 2, axis=1
            ))))
            for i in used
        }  # fmt: skip
        good = [i for i in used if per_marker[i] <= options.max_marker_residual_m]
        if len(good) == len(used) or not good:
            break
        used = good
    errors = np.concatenate(
        [transform_points(env_from_scan, found[i]) - reference.corners_env(i) for i in used]
    )
    return SheetFit(
        env_from_scan=env_from_scan,
        residual_m=float(np.sqrt(np.mean(np.sum(errors**2, axis=1)))),
        per_marker_m={i: per_marker[i] for i in used},
        used=tuple(used),
        planes_searched=len(planes),
        corners_scan={i: found[i] for i in used},
    )
