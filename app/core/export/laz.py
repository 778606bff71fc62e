"""A snapshot's cloud as LAZ (compressed LAS), converted once from its stored PLY and kept
beside it (``.../reconstruction/cloud.laz``, under the snapshot's storage prefix, so it goes
when the snapshot's files go).

The PLY's vertex records are read a chunk at a time and written with laspy's
chunked writer and the lazrs backend: LAS 1.2, point format 2 (x, y, z and 16-bit RGB) or 0
when the cloud has no colours; coordinates in metres in the environment frame with a scale
of 0.1 mm and an offset at the cloud's lower corner rounded down to whole metres. 8-bit
colours ``c`` become ``257·c`` (255 → 65535). Normals are not carried (LAS has no field for
them). The file is written under a private name and renamed into place, so concurrent
requests never see or leave half a file; the first of several at once converts and the
others wait for it.
"""

from __future__ import annotations

from pathlib import Path, PurePosixPath

import laspy
import numpy as np
from numpy.typing import NDArray

from app.core.export.derived import ensure_derived
from app.core.export.ply import PlyError, colors_of, iter_vertices, positions_of
from app.core.storage import Storage

MEDIA_TYPE = "application/vnd.laszip"
SCALE_M = 1e-4  # 0.1 mm
SYSTEM_IDENTIFIER = "twindelta environment frame"  # the LAS header's 32-byte fields
CHUNK_POINTS = 1 << 18  # about 7 MB of PLY records a chunk
_INT32_SPAN = 2**31 - 1


def laz_key(pointcloud_key: str) -> str:
    """The storage key of the cached LAZ beside a cloud's PLY (``cloud.ply`` → ``cloud.laz``)."""
    return str(PurePosixPath(pointcloud_key).with_suffix(".laz"))


def ensure_laz(
    storage: Storage, pointcloud_key: str, generator: str, chunk: int = CHUNK_POINTS
) -> str:
    """The key of the LAZ of the PLY at ``pointcloud_key``, converting it first unless a
    LAZ at least as new as the PLY is there. Conflict (409 ``PointCloudUnreadable``) when
    the PLY cannot be read or converted; InsufficientStorage (507) when the disk is full."""
    key = laz_key(pointcloud_key)
    ensure_derived(
        storage,
        pointcloud_key,
        key,
        lambda source, part: write_laz(source, part, generator, chunk),
        "the LAZ",
    )
    return key


def write_laz(ply: Path, out: Path, generator: str, chunk: int = CHUNK_POINTS) -> int:
    """Write the PLY cloud ``ply`` to ``out`` as LAZ (module docstring); returns the number
    of points written. Points with a non-finite coordinate are left out. PlyError when the
    PLY cannot be read or its extent does not fit 32-bit coordinates at 0.1 mm."""
    lower, upper, colored = _survey(ply, chunk)
    header = laspy.LasHeader(version="1.2", point_format=2 if colored else 0)
    header.scales = np.full(3, SCALE_M)
    header.offsets = np.floor(lower) if np.isfinite(lower).all() else np.zeros(3)
    if np.isfinite(upper).all() and ((upper - header.offsets) / SCALE_M > _INT32_SPAN).any():
        raise PlyError(f"{ply.name}: the cloud spans more than 214 km, beyond LAS at 0.1 mm")
    header.system_identifier = SYSTEM_IDENTIFIER
    header.generating_software = generator[:32]
    written = 0
    with laspy.open(
        out, mode="w", header=header, do_compress=True, laz_backend=laspy.LazBackend.Lazrs
    ) as writer:
        for records in iter_vertices(ply, chunk):
            xyz = positions_of(records)
            keep = np.isfinite(xyz).all(axis=1)
            points = laspy.ScaleAwarePointRecord.zeros(int(keep.sum()), header=header)
            points.x, points.y, points.z = xyz[keep, 0], xyz[keep, 1], xyz[keep, 2]
            if colored:
                rgb = _rgb16(records)[keep]
                points.red, points.green, points.blue = rgb[:, 0], rgb[:, 1], rgb[:, 2]
            writer.write_points(points)
            written += len(points)
    return written


def _survey(ply: Path, chunk: int) -> tuple[NDArray[np.float64], NDArray[np.float64], bool]:
    """The finite points' lower and upper corners (inf when there are none) and whether the
    records have colours."""
    lower, upper = np.full(3, np.inf), np.full(3, -np.inf)
    colored = False
    for records in iter_vertices(ply, chunk):
        xyz = positions_of(records)
        xyz = xyz[np.isfinite(xyz).all(axis=1)]
        if len(xyz):
            lower, upper = np.minimum(lower, xyz.min(axis=0)), np.maximum(upper, xyz.max(axis=0))
        colored = colored or colors_of(records[:1]) is not None
    return lower, upper, colored


def _rgb16(records: NDArray[np.void]) -> NDArray[np.uint16]:
    """(N, 3) 16-bit colours: 8-bit values × 257, 16-bit as they are, floats × 65535."""
    names = records.dtype.names or ()
    raw = next(
        (
            np.stack([records[c] for c in rgb], axis=1)
            for rgb in (("red", "green", "blue"), ("r", "g", "b"))
            if set(rgb) <= set(names)
        ),
        None,
    )
    if raw is not None and raw.dtype == np.uint8:
        return raw.astype(np.uint16) * np.uint16(257)
    if raw is not None and raw.dtype == np.uint16:
        return raw
    colors = colors_of(records)
    assert colors is not None  # _survey found colours
    return np.round(colors * 65535.0).astype(np.uint16)
