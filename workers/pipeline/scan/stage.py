"""The scan stage: a laser scan file → a coloured cloud in the environment frame, at the
density of a photo snapshot's cloud.

Steps: read the points in chunks (:mod:`.read`), scale them to metres and average them on
``voxel_m`` voxels as they stream (:mod:`.voxels`) → the frame: the given ``env_from_scan``,
or the marker sheet found in the averaged cloud (:mod:`.markers`), then refined on the
full-density points around the markers it found (a second pass over the file that keeps
only those) → the cloud moved into the environment frame and averaged again on the
environment's voxel grid.

Outputs under ``work_dir``: ``cloud.ply`` (binary, coloured when the scan has colours or
intensity, metres, environment frame: what the reconstruct stage writes), ``cameras.json``
(no cameras: a scan has no photos) and ``quality.json``.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d

from app.formats.scan import ScanFormat, ScanFrame
from workers.pipeline.errors import InputError
from workers.pipeline.geometry import Mat4, transform_points
from workers.pipeline.reconstruct.fusion import to_o3d, voxel_average
from workers.pipeline.reconstruct.markers import MarkerReference
from workers.pipeline.scan.markers import (
    ColorArray,
    FloatArray,
    NoUsableFrame,
    SheetFit,
    find_sheet,
)
from workers.pipeline.scan.options import ScanOptions
from workers.pipeline.scan.read import iter_scan
from workers.pipeline.scan.voxels import VoxelGrid

Progress = Callable[[str, float], None]


def _no_progress(stage: str, fraction: float) -> None:
    del stage, fraction


class EmptyScan(InputError):
    """The scan holds no valid (finite, not flagged invalid) point."""

    code = "EmptyScan"


@dataclass(frozen=True)
class ScanInput:
    """A stored scan: its file, format, frame and the point count its header declares (for
    progress; 0 when unknown)."""

    path: Path
    format: ScanFormat
    frame: ScanFrame
    points_declared: int = 0


@dataclass(frozen=True)
class ScanResult:
    """What the stage wrote, and its quality figures (``quality.json``)."""

    cloud_path: Path
    cameras_path: Path
    quality_path: Path
    quality: dict[str, Any]


def _read(scan: ScanInput, voxel_m: float, options: ScanOptions, progress: Progress) -> VoxelGrid:
    grid = VoxelGrid(voxel_m, max_voxels=options.max_voxels)
    scale = scan.frame.metres_per_unit
    total = max(scan.points_declared, 1)
    progress("read", 0.0)
    for chunk in iter_scan(scan.path, scan.format, options.chunk_points):
        grid.add(chunk.points * scale, chunk.colors)
        progress("read", min(grid.n_in / total, 1.0))
    return grid


def _near_markers(
    scan: ScanInput, centres_scan: FloatArray, radius_m: float, options: ScanOptions
) -> tuple[FloatArray, ColorArray]:
    """Every point of the file within ``radius_m`` of a marker centre (scan frame, metres),
    with its colour: the full-density neighbourhood of the markers (a second pass)."""
    scale = scan.frame.metres_per_unit
    kept_pts: list[FloatArray] = []
    kept_cols: list[ColorArray] = []
    for chunk in iter_scan(scan.path, scan.format, options.chunk_points):
        if chunk.colors is None:
            continue
        pts = chunk.points * scale
        near = np.zeros(len(pts), bool)
        for centre in centres_scan:
            near |= np.sum((pts - centre) ** 2, axis=1) <= radius_m**2
        kept_pts.append(pts[near])
        kept_cols.append(chunk.colors[near])
    if not kept_pts:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    return np.concatenate(kept_pts), np.concatenate(kept_cols)


def _marker_frame(
    scan: ScanInput,
    averaged: tuple[FloatArray, ColorArray | None],
    reference: MarkerReference | None,
    options: ScanOptions,
    progress: Progress,
) -> tuple[SheetFit, bool]:
    """The sheet's fit, refined on full-density points when that finds as many markers;
    and whether it was. NoUsableFrame when the sheet cannot be looked for or is not found."""
    points, colors = averaged
    if reference is None:
        raise NoUsableFrame("markers asked for, but the environment has no marker sheet")
    if colors is None:
        raise NoUsableFrame(
            "markers asked for, but the scan has neither colours nor intensity to see them in"
        )
    progress("markers", 0.0)
    coarse = find_sheet(
        points, colors, reference, options, lambda share: progress("markers", 0.8 * share)
    )
    progress("markers", 0.8)
    radius = np.sqrt(0.5) * reference.size_m + 0.1  # the marker, its paper and 10 cm of floor
    near_pts, near_cols = _near_markers(scan, coarse.centres_scan(), radius, options)
    try:
        fine = find_sheet(near_pts, near_cols, reference, options)
    except (NoUsableFrame, InputError):
        return coarse, False
    progress("markers", 1.0)
    if len(fine.used) >= len(coarse.used):
        return fine, True
    return coarse, False


def _write_cloud(path: Path, points: FloatArray, colors: ColorArray | None) -> None:
    """Binary PLY, coloured when ``colors`` is given (what the reconstruct stage writes)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if not o3d.io.write_point_cloud(str(path), to_o3d(points, colors), write_ascii=False):  # type: ignore[arg-type]
        raise OSError(f"cannot write {path}")


def scan_to_cloud(
    scan: ScanInput,
    work_dir: Path,
    voxel_m: float,
    reference: MarkerReference | None = None,
    options: ScanOptions | None = None,
    progress: Progress | None = None,
) -> ScanResult:
    """Read ``scan`` into a cloud in the environment frame under ``work_dir`` (see the
    module's docstring). ``voxel_m`` is the photo pipeline's voxel size (metres);
    ``reference`` the environment's marker sheet (needed for the ``markers`` frame).

    Raises ScanReadError (a damaged file), EmptyScan, NoUsableFrame (markers asked for and
    not found), InputError for a bad option.
    """
    options = options or ScanOptions()
    report = progress or _no_progress
    t0 = time.perf_counter()
    grid = _read(scan, voxel_m, options, report)
    points, colors = grid.result()
    if len(points) == 0:
        raise EmptyScan(f"the {scan.format.upper()} scan holds no valid points")
    t_read = time.perf_counter() - t0
    quality: dict[str, Any] = {
        "source": "scan",
        "format": scan.format,
        "units": scan.frame.units,
        "frame_method": scan.frame.method,
        "points_in": grid.n_in,
        "voxel_size_m": voxel_m,
        "colored": colors is not None,
        "marker_residual_m": None,
        "alignment_residual_m": 0.0,
    }
    env_from_scan: Mat4
    if scan.frame.method == "markers":
        fit, refined = _marker_frame(scan, (points, colors), reference, options, report)
        env_from_scan = fit.env_from_scan
        quality.update(
            marker_residual_m=fit.residual_m,
            alignment_residual_m=fit.residual_m,
            markers_used=list(fit.used),
            marker_per_marker_m={str(i): r for i, r in fit.per_marker_m.items()},
            marker_refined=refined,
            marker_planes_searched=fit.planes_searched,
        )
    else:
        env_from_scan = np.asarray(scan.frame.env_from_scan, dtype=np.float64)
    t_frame = time.perf_counter() - t0 - t_read
    report("write", 0.0)
    points_env, colors_env = voxel_average(transform_points(env_from_scan, points), voxel_m, colors)
    work_dir.mkdir(parents=True, exist_ok=True)
    cloud_path, cameras_path = work_dir / "cloud.ply", work_dir / "cameras.json"
    _write_cloud(cloud_path, points_env, colors_env if colors is not None else None)
    cameras_path.write_text(json.dumps({"images": {}}))  # a scan has no cameras
    quality.update(
        points=len(points_env),
        env_from_scan=[[float(v) for v in row] for row in env_from_scan],
        timings_s={
            "read": round(t_read, 3),
            "frame": round(t_frame, 3),
            "total": round(time.perf_counter() - t0, 3),
        },
    )
    quality_path = work_dir / "quality.json"
    quality_path.write_text(json.dumps(quality, indent=1))
    report("write", 1.0)
    return ScanResult(cloud_path, cameras_path, quality_path, quality)
