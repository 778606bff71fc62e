"""Read PLY files with NumPy: library models (vertices, optional normals and colours, optional
faces) and the vertex records of a snapshot's cloud in chunks (so a cloud of any size is
read with memory for one chunk).

ASCII, binary little-endian and binary big-endian files are read. Every failure is a
:class:`PlyError` naming the file and what is wrong; the element counts a header declares are
checked against the file's size first (:func:`app.formats.ply.read_ply_file_header`).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np
from numpy.typing import NDArray

from app.formats import FormatError
from app.formats.ply import (
    HEADER_MAX_BYTES,
    PLY_SCALARS,
    PlyElement,
    PlyHeader,
    PlyProperty,
    read_ply_file_header,
    read_ply_header,
    vertex_element,
)

_COLOR_NAMES = (
    ("red", "green", "blue"),
    ("r", "g", "b"),
    ("diffuse_red", "diffuse_green", "diffuse_blue"),
)


class PlyError(ValueError):
    """A PLY file that cannot be read: its header, its counts or its body."""


@dataclass(frozen=True)
class PlyModel:
    """A model in its file's units: ``positions`` (N, 3) float64; ``normals`` (N, 3) or
    None; ``colors`` (N, 3) float64 in [0, 1] or None; ``triangles`` (F, 3) int64 vertex
    indices (polygons fanned into triangles) or None for a point cloud."""

    positions: NDArray[np.float64]
    normals: NDArray[np.float64] | None
    colors: NDArray[np.float64] | None
    triangles: NDArray[np.int64] | None


def read_header(path: Path) -> tuple[PlyHeader, PlyElement]:
    """The header of ``path`` (:func:`app.formats.ply.read_ply_file_header`) and its leading
    vertex element; PlyError naming the file when the header is not one, declares more than
    the file holds, or has no leading vertex element with x, y and z and no lists."""
    try:
        header = read_ply_file_header(path)
        return header, vertex_element(header, path.name)
    except FormatError as exc:
        raise PlyError(exc.detail) from exc


def read_stream_header(fh: BinaryIO, where: str, chunk: int = 4096) -> tuple[PlyHeader, PlyElement]:
    """The header and leading vertex element of the PLY stream ``fh``, reading ``chunk``
    bytes at a time only until the ``end_header`` line (at most
    :data:`app.formats.ply.HEADER_MAX_BYTES`), so a stored cloud is not fetched whole. The
    counts are not checked against the size (the stream's is unknown here); PlyError as
    :func:`read_header`."""
    head = b""
    while len(head) < HEADER_MAX_BYTES:
        data = fh.read(min(chunk, HEADER_MAX_BYTES - len(head)))
        if not data:
            break
        head += data
        end = head.find(b"end_header")
        if end >= 0 and head.find(b"\n", end) >= 0:
            break
    try:
        header = read_ply_header(head, where)
        return header, vertex_element(header, where)
    except FormatError as exc:
        raise PlyError(exc.detail) from exc


def _dtype(header: PlyHeader, element: PlyElement) -> np.dtype[np.void]:
    """The packed record of a scalar-only element in the file's byte order."""
    return np.dtype(header.fields(element))


def _scalar(header: PlyHeader, kind: str) -> np.dtype[np.generic]:
    """One PLY scalar type in the file's byte order."""
    return np.dtype(header.byte_order + PLY_SCALARS[kind].code)


def iter_vertices(path: Path, chunk: int = 1 << 20) -> Iterator[NDArray[np.void]]:
    """The vertex records of ``path``, at most ``chunk`` at a time, as structured arrays
    with the file's property names (read a chunk at a time, never whole).
    PlyError when the file has no leading vertex element with x, y and z."""
    header, vertex = read_header(path)
    if header.fmt == "ascii":
        with path.open("rb") as fh:
            fh.seek(header.header_bytes)
            yield from _ascii_vertices(path, fh, header, vertex, chunk)
        return
    dtype = _dtype(header, vertex)
    with path.open("rb") as fh:
        fh.seek(header.header_bytes)
        for start in range(0, vertex.count, chunk):
            n = min(chunk, vertex.count - start)
            records = np.fromfile(fh, dtype=dtype, count=n)
            if len(records) != n:  # the header's count was checked against the size
                raise PlyError(f"{path.name}: the file ends inside its vertices")
            yield records


def _ascii_vertices(
    path: Path, fh: BinaryIO, header: PlyHeader, vertex: PlyElement, chunk: int
) -> Iterator[NDArray[np.void]]:
    dtype = _dtype(header, vertex)
    names = dtype.names or ()
    left = vertex.count
    while left > 0:
        n = min(chunk, left)
        lines = [fh.readline() for _ in range(n)]
        try:
            values = np.array([line.split() for line in lines], dtype=np.float64)
        except ValueError as exc:
            raise PlyError(f"{path.name}: a vertex line is not {len(names)} numbers") from exc
        if values.shape != (n, len(names)):
            raise PlyError(f"{path.name}: a vertex line is not {len(names)} numbers")
        out = np.empty(n, dtype=dtype)
        for i, name in enumerate(names):
            out[name] = values[:, i]
        yield out
        left -= n


def positions_of(records: NDArray[np.void]) -> NDArray[np.float64]:
    """(N, 3) float64 x, y, z of vertex records."""
    return np.stack([records[a].astype(np.float64) for a in ("x", "y", "z")], axis=1)


def colors_of(records: NDArray[np.void]) -> NDArray[np.float64] | None:
    """(N, 3) colours in [0, 1] (8-bit and 16-bit integers scaled by 255 and 65535, floats
    as they are), or None when the records have none."""
    names = set(records.dtype.names or ())
    for rgb in _COLOR_NAMES:
        if set(rgb) <= names:
            raw = np.stack([records[c] for c in rgb], axis=1)
            if raw.dtype.kind in "ui":
                return raw.astype(np.float64) / float(np.iinfo(raw.dtype).max)
            return np.clip(raw.astype(np.float64), 0.0, 1.0)
    return None


def read_model(path: Path) -> PlyModel:
    """A mesh or point-cloud PLY file whole (a library model). Faces named
    ``vertex_indices`` or ``vertex_index`` are fanned into triangles; a face naming a vertex
    the file lacks is a PlyError, as is a body shorter than its header says."""
    header, vertex = read_header(path)
    records = np.concatenate(list(iter_vertices(path)) or [np.empty(0, _dtype(header, vertex))])
    names = set(records.dtype.names or ())
    normals = (
        np.stack([records[a].astype(np.float64) for a in ("nx", "ny", "nz")], axis=1)
        if {"nx", "ny", "nz"} <= names
        else None
    )
    faces = header.element("face")
    triangles = _read_triangles(path, header) if faces is not None and faces.count else None
    if (
        triangles is not None
        and triangles.size
        and (triangles.min() < 0 or triangles.max() >= vertex.count)
    ):
        raise PlyError(f"{path.name}: a face names a vertex outside 0..{vertex.count - 1}")
    return PlyModel(positions_of(records), normals, colors_of(records), triangles)


def _read_triangles(path: Path, header: PlyHeader) -> NDArray[np.int64]:
    """(F, 3) triangles of the face element: the fast path reads packed triangle records,
    anything else (polygons, extra properties, ASCII) is walked element by element."""
    with path.open("rb") as fh:
        fh.seek(header.header_bytes)
        body = fh.read()
    if header.fmt == "ascii":
        return _ascii_triangles(path, header, body)
    offset = 0
    for element in header.elements:
        if element.name == "face":
            return _binary_triangles(path, header, element, body, offset)
        offset = _skip_binary(path, header, element, body, offset)
    raise PlyError(f"{path.name}: no face element")


def _skip_binary(
    path: Path, header: PlyHeader, element: PlyElement, body: bytes, offset: int
) -> int:
    if element.scalar_only:
        return offset + element.count * _dtype(header, element).itemsize
    for _ in range(element.count):
        for prop in element.properties:
            offset = _skip_property(path, header, prop, body, offset)
    return offset


def _skip_property(path: Path, header: PlyHeader, prop: PlyProperty, body: bytes, at: int) -> int:
    item = _scalar(header, prop.kind)
    if prop.count_kind is None:
        return at + item.itemsize
    count_type = _scalar(header, prop.count_kind)
    if at + count_type.itemsize > len(body):
        raise PlyError(f"{path.name}: the file ends inside element data")
    n = int(np.frombuffer(body, count_type, 1, at)[0])
    return at + count_type.itemsize + n * item.itemsize


def _binary_triangles(
    path: Path, header: PlyHeader, face: PlyElement, body: bytes, offset: int
) -> NDArray[np.int64]:
    props = face.properties
    index_names = {"vertex_indices", "vertex_index"}
    if len(props) == 1 and props[0].name in index_names and props[0].count_kind is not None:
        count_t = _scalar(header, props[0].count_kind)
        index_t = _scalar(header, props[0].kind)
        packed = np.dtype([("n", count_t), ("v", index_t, (3,))])
        if offset + face.count * packed.itemsize <= len(body):
            rows = np.frombuffer(body, packed, face.count, offset)
            if (rows["n"] == 3).all():
                return rows["v"].astype(np.int64)
    polygons: list[list[int]] = []
    for _ in range(face.count):
        for prop in props:
            end = _skip_property(path, header, prop, body, offset)
            if prop.name in index_names and prop.count_kind is not None:
                size = PLY_SCALARS[prop.count_kind].size
                item = _scalar(header, prop.kind)
                polygons.append(np.frombuffer(body[offset + size : end], item).tolist())
            offset = end
    if offset > len(body):
        raise PlyError(f"{path.name}: the file ends inside the faces")
    return _fan(path, polygons)


def _ascii_triangles(path: Path, header: PlyHeader, body: bytes) -> NDArray[np.int64]:
    lines = iter(body.splitlines())
    polygons: list[list[int]] = []
    for element in header.elements:
        for _ in range(element.count):
            words = next(lines, b"").split()
            if element.name != "face":
                continue
            try:
                n = int(words[0])
                polygons.append([int(w) for w in words[1 : 1 + n]])
            except (IndexError, ValueError):
                raise PlyError(f"{path.name}: a face line is not a count and indices") from None
        if element.name == "face":
            return _fan(path, polygons)
    raise PlyError(f"{path.name}: no face element")


def _fan(path: Path, polygons: list[list[int]]) -> NDArray[np.int64]:
    """Polygons (v0, v1, ..., vk) as triangles (v0, vi, vi+1); fewer than 3 vertices are
    dropped."""
    out = [(p[0], p[i], p[i + 1]) for p in polygons for i in range(1, len(p) - 1)]
    if not out:
        raise PlyError(f"{path.name}: the faces hold no triangle")
    return np.asarray(out, dtype=np.int64)
