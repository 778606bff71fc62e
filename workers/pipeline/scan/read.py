"""Scan readers: E57 (pye57, every scan with its pose), LAS/LAZ (laspy) and PLY, each
yielding the points in chunks, so a scan of any size is read in bounded memory.

A chunk's ``points`` are (N, 3) float64 in the file's stored units: E57 scans already moved
by their own pose into the file's common frame, LAS with its scale and offset applied.
``colors`` are (N, 3) uint8 RGB: 16-bit colours are scaled to 8 bits, a file without colours
but with intensity gets grey levels from it, and one with neither gives None.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import laspy
import numpy as np
import pye57
from numpy.typing import NDArray

from app.formats import FormatError
from app.formats.ply import PLY_SCALARS, read_ply_file_header, vertex_element
from app.formats.scan import ScanFormat
from workers.pipeline.errors import InputError

FloatArray = NDArray[np.float64]
ColorArray = NDArray[np.uint8]

_CARTESIAN = ("cartesianX", "cartesianY", "cartesianZ")
_SPHERICAL = ("sphericalRange", "sphericalAzimuth", "sphericalElevation")
_RGB = ("colorRed", "colorGreen", "colorBlue")


class ScanReadError(InputError):
    """The scan's points cannot be read (a damaged file, a missing field)."""

    code = "InvalidScan"


@dataclass(frozen=True, eq=False)
class ScanChunk:
    """Up to a chunk of points: (N, 3) float64 in stored units, (N, 3) uint8 RGB or None."""

    points: FloatArray
    colors: ColorArray | None


def _to_uint8(values: NDArray[np.generic], full_scale: float) -> ColorArray:
    scaled = np.asarray(values, np.float64) * (255.0 / max(full_scale, 1e-12))
    return np.clip(np.rint(scaled), 0, 255).astype(np.uint8)


def _grey(intensity: NDArray[np.generic], full_scale: float) -> ColorArray:
    grey = _to_uint8(intensity, full_scale)
    return np.repeat(grey[:, None], 3, axis=1)


def iter_scan(path: Path, fmt: ScanFormat, chunk_points: int = 1_000_000) -> Iterator[ScanChunk]:
    """The points of the scan at ``path`` in chunks of at most ``chunk_points``. Raises
    ScanReadError naming the problem."""
    if chunk_points <= 0:
        raise InputError(f"chunk_points must be positive, got {chunk_points}")
    try:
        if fmt == "e57":
            yield from _iter_e57(path, chunk_points)
        elif fmt in ("las", "laz"):
            yield from _iter_las(path, chunk_points)
        elif fmt == "ply":
            yield from _iter_ply(path, chunk_points)
        else:
            raise ScanReadError(f"unknown scan format {fmt!r}")
    except (OSError, ValueError, RuntimeError, pye57.libe57.E57Exception) as exc:
        if isinstance(exc, InputError):
            raise
        raise ScanReadError(f"{fmt.upper()} scan: cannot read its points ({exc})") from exc


def _e57_limit(header: pye57.ScanHeader, node: str, field: str, default: float) -> float:
    try:
        return float(header.node[node][field].value())
    except Exception:  # libe57 raises its own error for an absent node
        return default


def _iter_e57(path: Path, chunk: int) -> Iterator[ScanChunk]:
    with pye57.E57(str(path)) as e57:
        for index in range(e57.scan_count):
            header = e57.get_header(index)
            fields = set(header.point_fields)
            coords = _CARTESIAN if set(_CARTESIAN) <= fields else _SPHERICAL
            if not set(coords) <= fields:
                raise ScanReadError(f"E57 scan {index} has no cartesian or spherical coordinates")
            invalid = "cartesianInvalidState" if coords == _CARTESIAN else "sphericalInvalidState"
            wanted = list(coords) + [f for f in (*_RGB, "intensity", invalid) if f in fields]
            rgb_max = _e57_limit(header, "colorLimits", "colorRedMaximum", 255.0)
            i_min = _e57_limit(header, "intensityLimits", "intensityMinimum", 0.0)
            i_max = _e57_limit(header, "intensityLimits", "intensityMaximum", 1.0)
            rotation = header.rotation_matrix if header.has_pose() else np.eye(3)
            translation = np.asarray(header.translation if header.has_pose() else np.zeros(3))
            data, buffers = e57.make_buffers(wanted, chunk)
            reader = header.points.reader(buffers)
            try:
                while (n := int(reader.read())) > 0:
                    part = {name: data[name][:n] for name in wanted}
                    keep = part[invalid] == 0 if invalid in part else slice(None)
                    xyz = np.column_stack([part[name] for name in coords])[keep]
                    if coords == _SPHERICAL:
                        r, az, el = xyz[:, 0], xyz[:, 1], xyz[:, 2]
                        xyz = np.column_stack(
                            [
                                r * np.cos(el) * np.cos(az),
                                r * np.cos(el) * np.sin(az),
                                r * np.sin(el),
                            ]
                        )
                    xyz = xyz @ np.asarray(rotation).T + translation
                    colors = None
                    if set(_RGB) <= fields:
                        colors = _to_uint8(np.column_stack([part[c] for c in _RGB])[keep], rgb_max)
                    elif "intensity" in fields:
                        colors = _grey(part["intensity"][keep] - i_min, i_max - i_min)
                    yield ScanChunk(np.asarray(xyz, np.float64), colors)
            finally:
                reader.close()


def _iter_las(path: Path, chunk: int) -> Iterator[ScanChunk]:
    with laspy.open(str(path)) as reader:
        names = set(reader.header.point_format.dimension_names)
        full_scale: float | None = None  # decided on the first chunk: 8- or 16-bit values
        for points in reader.chunk_iterator(chunk):
            xyz = np.column_stack(
                [np.asarray(points.x), np.asarray(points.y), np.asarray(points.z)]
            ).astype(np.float64)
            colors = None
            if {"red", "green", "blue"} <= names:
                rgb = np.column_stack([points.red, points.green, points.blue])
                if full_scale is None:
                    full_scale = 255.0 if len(rgb) and int(rgb.max()) <= 255 else 65535.0
                colors = _to_uint8(rgb, full_scale)
            elif "intensity" in names:
                intensity = np.asarray(points.intensity)
                if full_scale is None:
                    full_scale = (
                        255.0 if len(intensity) and int(intensity.max()) <= 255 else 65535.0
                    )
                colors = _grey(intensity, full_scale)
            yield ScanChunk(xyz, colors)


def _ply_colors(columns: Mapping[str, NDArray[Any]]) -> ColorArray | None:
    for names in (
        ("red", "green", "blue"),
        ("r", "g", "b"),
        ("diffuse_red", "diffuse_green", "diffuse_blue"),
    ):
        if all(n in columns for n in names):
            rgb = np.column_stack([columns[n] for n in names])
            if rgb.dtype.kind == "f":
                return _to_uint8(rgb, 1.0)
            return _to_uint8(rgb, 65535.0 if rgb.dtype.itemsize > 1 else 255.0)
    if "intensity" in columns:
        values = columns["intensity"]
        return _grey(values, 1.0 if values.dtype.kind == "f" else float(np.iinfo(values.dtype).max))
    return None


def _iter_ply(path: Path, chunk: int) -> Iterator[ScanChunk]:
    try:
        header = read_ply_file_header(path, "scan")
        vertex = vertex_element(header, "scan")
    except FormatError as exc:
        raise ScanReadError(exc.detail) from exc
    names = [p.name for p in vertex.properties]
    if header.fmt == "ascii":
        kinds = {p.name: PLY_SCALARS[p.kind].code for p in vertex.properties}
        with path.open("rb") as fh:
            fh.seek(header.header_bytes)
            left = vertex.count
            while left > 0:
                lines = list(itertools.islice(fh, min(chunk, left)))
                if not lines:
                    raise ScanReadError(f"the PLY file ends {left} vertices early")
                rows = np.loadtxt(lines, dtype=np.float64, ndmin=2)
                left -= len(rows)
                columns = {n: rows[:, i] for i, n in enumerate(names)}
                for rgb in ("red", "green", "blue", "r", "g", "b"):  # ASCII ints: their PLY type
                    if rgb in columns:
                        columns[rgb] = columns[rgb].astype(kinds[rgb])
                yield _ply_chunk(columns)
        return
    vertices = np.memmap(
        path,
        dtype=np.dtype(header.fields(vertex)),
        mode="r",
        offset=header.header_bytes,
        shape=(vertex.count,),
    )
    for start in range(0, vertex.count, chunk):
        block = np.asarray(vertices[start : start + chunk])
        yield _ply_chunk({n: block[n].astype(block[n].dtype.newbyteorder("=")) for n in names})


def _ply_chunk(columns: Mapping[str, NDArray[Any]]) -> ScanChunk:
    xyz = np.column_stack([columns["x"], columns["y"], columns["z"]]).astype(np.float64)
    return ScanChunk(xyz, _ply_colors(columns))
