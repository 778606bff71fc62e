"""Read PLY files with NumPy: library models (vertices, optional normals and colours, optional
faces) and the vertex records of a snapshot's cloud in chunks (so a cloud of any size is
read with memory for one chunk).

ASCII, binary little-endian and binary big-endian files are read. Every failure is a
:class:`PlyError` naming the file and what is wrong; the element counts a header declares are
checked against the file's size first (:func:`app.formats.ply.ply_count_problem`).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np
from numpy.typing import NDArray

from app.formats.ply import ply_count_problem

HEADER_MAX_BYTES = 64 * 1024

# NumPy dtype (without byte order) of each PLY scalar type
_SCALARS = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
_COLOR_NAMES = (
    ("red", "green", "blue"),
    ("r", "g", "b"),
    ("diffuse_red", "diffuse_green", "diffuse_blue"),
)


class PlyError(ValueError):
    """A PLY file that cannot be read: its header, its counts or its body."""


@dataclass(frozen=True)
class PlyProperty:
    """One property: ``kind`` the scalar type, or for a list ``count_kind`` its length's."""

    name: str
    kind: str
    count_kind: str | None = None


@dataclass(frozen=True)
class PlyElement:
    name: str
    count: int
    properties: tuple[PlyProperty, ...]

    @property
    def scalar_only(self) -> bool:
        return all(p.count_kind is None for p in self.properties)


@dataclass(frozen=True)
class PlyHeader:
    """``fmt`` ascii | binary_little_endian | binary_big_endian; ``data_offset`` the byte
    where the body starts."""

    fmt: str
    elements: tuple[PlyElement, ...]
    data_offset: int

    @property
    def byte_order(self) -> str:
        return ">" if self.fmt == "binary_big_endian" else "<"

    def element(self, name: str) -> PlyElement | None:
        return next((e for e in self.elements if e.name == name), None)

    def dtype(self, element: PlyElement) -> np.dtype[np.void]:
        """The packed record of a scalar-only element in this file's byte order."""
        return np.dtype([(p.name, self.byte_order + _SCALARS[p.kind]) for p in element.properties])


@dataclass(frozen=True)
class PlyModel:
    """A model in its file's units: ``positions`` (N, 3) float64; ``normals`` (N, 3) or
    None; ``colors`` (N, 3) float64 in [0, 1] or None; ``triangles`` (F, 3) int64 vertex
    indices (polygons fanned into triangles) or None for a point cloud."""

    positions: NDArray[np.float64]
    normals: NDArray[np.float64] | None
    colors: NDArray[np.float64] | None
    triangles: NDArray[np.int64] | None


def read_header(path: Path) -> PlyHeader:
    """The header of ``path``; PlyError when it is not a PLY header, names an unknown
    type, or declares more elements than the file can hold."""
    size = path.stat().st_size
    with path.open("rb") as fh:
        head = fh.read(HEADER_MAX_BYTES)
    end = head.find(b"end_header")
    if not head.startswith(b"ply") or end < 0:
        raise PlyError(f"{path.name}: not a PLY file with a complete header")
    newline = head.find(b"\n", end)
    if newline < 0:
        raise PlyError(f"{path.name}: the header's last line has no line end")
    problem = ply_count_problem(head, size)
    if problem is not None:
        raise PlyError(f"{path.name}: {problem}")
    fmt = ""
    elements: list[tuple[str, int, list[PlyProperty]]] = []
    for line in head[:end].decode("latin-1").splitlines()[1:]:
        words = line.split()
        if words[:1] == ["format"] and len(words) >= 2:
            fmt = words[1]
        elif words[:1] == ["element"] and len(words) == 3:
            elements.append((words[1], int(words[2]), []))
        elif words[:1] == ["property"] and elements:
            if words[1] == "list" and len(words) == 5:
                elements[-1][2].append(PlyProperty(words[4], words[3], words[2]))
            elif len(words) == 3:
                elements[-1][2].append(PlyProperty(words[2], words[1]))
            else:
                raise PlyError(f"{path.name}: cannot read the header line {line!r}")
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise PlyError(f"{path.name}: unknown PLY format {fmt!r}")
    return PlyHeader(
        fmt,
        tuple(PlyElement(n, c, tuple(p)) for n, c, p in elements),
        newline + 1,
    )


def _vertex_element(path: Path, header: PlyHeader) -> PlyElement:
    vertex = header.element("vertex")
    if vertex is None or not {"x", "y", "z"} <= {p.name for p in vertex.properties}:
        raise PlyError(f"{path.name}: no vertex element with x, y and z")
    if header.elements[0] is not vertex or not vertex.scalar_only:
        raise PlyError(f"{path.name}: the vertex element must come first, without lists")
    return vertex


def iter_vertices(path: Path, chunk: int = 1 << 20) -> Iterator[NDArray[np.void]]:
    """The vertex records of ``path``, at most ``chunk`` at a time, as structured arrays
    with the file's property names (read a chunk at a time, never whole).
    PlyError when the file has no leading vertex element with x, y and z."""
    header = read_header(path)
    vertex = _vertex_element(path, header)
    if header.fmt == "ascii":
        with path.open("rb") as fh:
            fh.seek(header.data_offset)
            yield from _ascii_vertices(path, fh, header, vertex, chunk)
        return
    dtype = header.dtype(vertex)
    with path.open("rb") as fh:
        fh.seek(header.data_offset)
        for start in range(0, vertex.count, chunk):
            n = min(chunk, vertex.count - start)
            records = np.fromfile(fh, dtype=dtype, count=n)
            if len(records) != n:  # the header's count was checked against the size
                raise PlyError(f"{path.name}: the file ends inside its vertices")
            yield records


def _ascii_vertices(
    path: Path, fh: BinaryIO, header: PlyHeader, vertex: PlyElement, chunk: int
) -> Iterator[NDArray[np.void]]:
    dtype = np.dtype([(p.name, _SCALARS[p.kind]) for p in vertex.properties])
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
    header = read_header(path)
    vertex = _vertex_element(path, header)
    records = np.concatenate(list(iter_vertices(path)) or [np.empty(0, header.dtype(vertex))])
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
        fh.seek(header.data_offset)
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
        return offset + element.count * header.dtype(element).itemsize
    for _ in range(element.count):
        for prop in element.properties:
            offset = _skip_property(path, header, prop, body, offset)
    return offset


def _skip_property(path: Path, header: PlyHeader, prop: PlyProperty, body: bytes, at: int) -> int:
    item = np.dtype(header.byte_order + _SCALARS[prop.kind])
    if prop.count_kind is None:
        return at + item.itemsize
    count_type = np.dtype(header.byte_order + _SCALARS[prop.count_kind])
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
        count_t = header.byte_order + _SCALARS[props[0].count_kind]
        index_t = header.byte_order + _SCALARS[props[0].kind]
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
                size = np.dtype(_SCALARS[prop.count_kind]).itemsize
                item = np.dtype(header.byte_order + _SCALARS[prop.kind])
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
