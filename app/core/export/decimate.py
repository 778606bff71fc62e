"""A snapshot's cloud at a size a browser draws: at most N points, binary PLY, cached on disk.

The points kept are a uniformly random subset drawn with a fixed seed: every point of the
cloud gets one uniform random key (seed :data:`SEED`) and the N with the smallest keys are
kept. So the same N always gives the same file, a smaller N gives a subset of a larger one (a
level of detail), and every part of the cloud keeps the same share of its points (even in
space wherever the cloud is, which the reconstruction's voxel fusion already makes even).

The file is ``float x, y, z`` (environment frame, metres) and ``uchar red, green, blue``,
little-endian, 15 bytes a point, kept in file order. A cloud without colours gets
:data:`GREY`. It is written once per N beside the cloud
(``.../reconstruction/decimated/<N>.ply``, so it goes when the snapshot's files go), under
a private name renamed into place; a cached file older than the cloud is made again.

The cloud is read by memory map (binary PLY: only the kept records' pages are touched) or
chunk by chunk (ASCII), so its size is limited by the disk, not by memory for the whole.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import numpy as np
from numpy.typing import NDArray

from app.core.errors import Conflict
from app.core.export.derived import ensure_derived
from app.core.export.ply import (
    PlyError,
    colors_of,
    iter_vertices,
    read_header,
    read_stream_header,
)
from app.core.storage import Storage

SEED = 20
MIN_POINTS = 1_000
MAX_POINTS = 5_000_000
# A requested N is rounded down to m·10^k for m in STEPS, so a snapshot keeps at most
# 10 cached files a decade (about 2.5 times the largest one in all), whatever is asked.
STEPS = (1.0, 1.25, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 8.0)
GREY = 180  # the colour of a cloud that has none
RECORD = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1")])


@dataclass(frozen=True)
class Decimated:
    """The cached file's storage ``key``, the points in it and in the whole cloud."""

    key: str
    n_points: int
    total_points: int


def level(max_points: int) -> int:
    """The largest m·10^k ≤ ``max_points`` (m in :data:`STEPS`; ``max_points`` ≥ 1)."""
    k = len(str(int(max_points))) - 1
    return max(int(m * 10**k) for m in STEPS if m * 10**k <= max_points)


def decimated_key(pointcloud_key: str, n_points: int) -> str:
    """The cache key of the ``n_points`` version of the cloud at ``pointcloud_key``."""
    return str(PurePosixPath(pointcloud_key).parent / "decimated" / f"{n_points}.ply")


def kept_mask(total: int, n_points: int, seed: int = SEED) -> NDArray[np.bool_]:
    """(total,) which points a cloud of ``total`` keeps at ``n_points`` (all when
    ``n_points`` ≥ ``total``): the ``n_points`` with the smallest of one seeded uniform key
    per point, so a smaller ``n_points`` keeps a subset of a larger one."""
    if n_points >= total:
        return np.ones(total, dtype=bool)
    keys = np.random.default_rng(seed).random(total)
    mask = np.zeros(total, dtype=bool)
    mask[np.argpartition(keys, n_points - 1)[:n_points]] = True
    return mask


def ply_header(n_points: int, comment: str = "") -> bytes:
    """The header of a decimated file of ``n_points`` points."""
    lines = ["ply", "format binary_little_endian 1.0"]
    if comment:
        lines.append(f"comment {comment}")
    lines += [
        f"element vertex {n_points}",
        "property float x",
        "property float y",
        "property float z",
        "property uchar red",
        "property uchar green",
        "property uchar blue",
        "end_header",
    ]
    return ("\n".join(lines) + "\n").encode("ascii")


def total_points(storage: Storage, pointcloud_key: str) -> int:
    """Points in the stored cloud: its header's vertex count, read from the start of the
    object's stream (the cloud is not fetched). FileNotFoundError when it is missing; 409
    PointCloudUnreadable when the header cannot be read."""
    try:
        with storage.open(pointcloud_key) as fh:
            return read_stream_header(fh, PurePosixPath(pointcloud_key).name)[1].count
    except PlyError as exc:
        raise Conflict(str(exc), code="PointCloudUnreadable") from exc


def ensure_decimated(storage: Storage, pointcloud_key: str, max_points: int) -> Decimated:
    """The cached decimated cloud of the PLY at ``pointcloud_key`` with :func:`level`
    (``max_points``) points, or all of them when it has fewer, made first unless a file at
    least as new as the cloud is there.
    Conflict (409 ``PointCloudUnreadable``) when the cloud cannot be read;
    InsufficientStorage (507) when the disk is full."""
    total = total_points(storage, pointcloud_key)
    n = min(level(max_points), total)
    key = decimated_key(pointcloud_key, n)

    def write(source: Path, part: Path) -> None:
        records = decimate(source, n)
        with part.open("wb") as out:
            out.write(ply_header(len(records), f"twindelta: {n} of {total} points"))
            out.write(records.tobytes())

    ensure_derived(storage, pointcloud_key, key, write, "the decimated cloud")
    return Decimated(key, n, total)


def decimate(path: Path, n_points: int) -> NDArray[np.void]:
    """The kept points (:func:`kept_mask`) of the PLY at ``path`` as :data:`RECORD` records
    in file order. PlyError when the file is not a readable point cloud."""
    header, vertex = read_header(path)
    keep = kept_mask(vertex.count, n_points)
    if header.fmt != "ascii":
        records = np.memmap(
            path,
            dtype=np.dtype(header.fields(vertex)),
            mode="r",
            offset=header.header_bytes,
            shape=(vertex.count,),
        )
        return _records(records[np.flatnonzero(keep)])
    parts, start = [], 0
    for chunk in iter_vertices(path):
        parts.append(_records(chunk[keep[start : start + len(chunk)]]))
        start += len(chunk)
    return np.concatenate(parts) if parts else np.empty(0, RECORD)


def _records(vertices: NDArray[np.void]) -> NDArray[np.void]:
    out = np.empty(len(vertices), RECORD)
    for axis in ("x", "y", "z"):
        out[axis] = vertices[axis]
    names = set(vertices.dtype.names or ())
    if {"red", "green", "blue"} <= names and all(
        vertices.dtype[c] == np.uint8 for c in ("red", "green", "blue")
    ):  # 8-bit colours (what the reconstruction writes) as they are
        out["r"], out["g"], out["b"] = vertices["red"], vertices["green"], vertices["blue"]
        return out
    colors = colors_of(vertices)
    rgb = (
        np.full((len(vertices), 3), GREY, np.uint8)
        if colors is None
        else np.clip(np.rint(colors * 255.0), 0, 255).astype(np.uint8)
    )
    out["r"], out["g"], out["b"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    return out
