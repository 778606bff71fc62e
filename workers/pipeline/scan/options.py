"""Options of the scan stage: one frozen dataclass and its named presets.

The cloud's density is not an option here: the stage is given the voxel size of the
environment's reconstruct options (``ReconstructOptions.voxel_size_m``), so a scan snapshot
has the density of a photo snapshot.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

from workers.pipeline.errors import InputError


@dataclass(frozen=True)
class ScanOptions:
    """Knobs of reading a scan and finding the marker sheet in it. Lengths in metres."""

    seed: int = 0  # RNG seed of plane RANSAC
    chunk_points: int = 1_000_000  # points read at a time (memory: ~100 bytes a point)
    # the averaged cloud's limit: 64 bytes a voxel, twice that while chunks are merged
    # (measured: 3.4 GB peak for 15 M voxels); ScanTooDense beyond
    max_voxels: int = 40_000_000
    # marker sheet in the scan
    plane_voxel_m: float = 0.02  # the cloud is thinned to this before plane RANSAC
    plane_distance_m: float = 0.01  # RANSAC inlier distance; also the slab rasterised
    plane_iterations: int = 1000  # RANSAC iterations per plane
    max_planes: int = 10  # largest planes searched for markers, in order of size
    plane_min_points: int = 200  # a plane needs this many thinned points to be searched
    max_point_spacing_m: float = 0.008  # sparser planes are skipped (a marker cell: s/6)
    raster_m: float = 0.0015  # raster pixel (1.5 mm) the coloured plane points are drawn on
    raster_tile_px: int = 4000  # rasters are detected in tiles of at most this side
    max_marker_residual_m: float = 0.01  # a marker whose corners fit worse is dropped


PRESETS: dict[str, ScanOptions] = {"default": ScanOptions()}


def scan_options(name: str = "default", **overrides: Any) -> ScanOptions:
    """The named preset with fields replaced; InputError for an unknown preset or field."""
    if name not in PRESETS:
        raise InputError(f"unknown scan preset {name!r}; choose one of {sorted(PRESETS)}")
    try:
        return replace(PRESETS[name], **overrides)
    except TypeError as exc:
        raise InputError(f"scan options: {exc}") from exc
