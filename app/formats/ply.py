"""PLY headers: the one parser every PLY reader uses (the object and scan uploads, the
worker's model and scan readers, the glTF export and the LAZ conversion). Standard library
only; the NumPy readers build their record types from :meth:`PlyHeader.fields`.

A header is ``ply``, ``format ascii|binary_little_endian|binary_big_endian 1.0``, then
``element NAME COUNT`` lines each followed by its ``property TYPE NAME`` or ``property list
COUNT_TYPE TYPE NAME`` lines, and ``end_header`` with its line end; ``comment`` and
``obj_info`` lines are skipped. The counts a header declares are checked against the file's
size before any reader allocates for them (:func:`ply_body_problem`: a 1 kB file declaring
2 × 10⁹ vertices would otherwise end in ``bad_alloc`` or the OOM killer). Errors are
:class:`~app.formats.errors.FormatError` naming the problem.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from app.formats.errors import FormatError, show

HEADER_MAX_BYTES = 64 * 1024  # a longer header is refused (no 'end_header' in it)
FORMATS = ("ascii", "binary_little_endian", "binary_big_endian")
CODE_INVALID = "InvalidPly"


@dataclass(frozen=True)
class PlyScalar:
    """One PLY scalar type: ``size`` bytes in a binary body, ``code`` the NumPy type code
    without byte order (``"f4"``)."""

    size: int
    code: str


_NAMES_BY_CODE = {
    "i1": ("char", "int8"), "u1": ("uchar", "uint8"),
    "i2": ("short", "int16"), "u2": ("ushort", "uint16"),
    "i4": ("int", "int32"), "u4": ("uint", "uint32"),
    "f4": ("float", "float32"), "f8": ("double", "float64"),
}  # fmt: skip
# Every PLY scalar type by name (both the classic and the sized names).
PLY_SCALARS = {
    name: PlyScalar(int(code[1:]), code) for code, names in _NAMES_BY_CODE.items() for name in names
}


@dataclass(frozen=True)
class PlyProperty:
    """One property: ``kind`` its scalar type, or for a list its items' type with
    ``count_kind`` the type of its length."""

    name: str
    kind: str
    count_kind: str | None = None

    def min_bytes(self, binary: bool) -> int:
        """The fewest bytes one value takes: binary, the scalar (a list, its length);
        ASCII, two characters (a digit and a separator)."""
        if not binary:
            return 2
        return PLY_SCALARS[self.count_kind or self.kind].size


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
    """``fmt`` one of :data:`FORMATS`, ``version`` as written (``"1.0"``), the elements in
    file order, ``header_bytes`` where the body starts."""

    fmt: str
    version: str
    elements: tuple[PlyElement, ...]
    header_bytes: int

    @property
    def binary(self) -> bool:
        return self.fmt != "ascii"

    @property
    def byte_order(self) -> str:
        """``>`` for big-endian bodies, else ``<``."""
        return ">" if self.fmt == "binary_big_endian" else "<"

    def element(self, name: str) -> PlyElement | None:
        return next((e for e in self.elements if e.name == name), None)

    def fields(self, element: PlyElement) -> list[tuple[str, str]]:
        """``(name, byte order + type code)`` of a scalar-only element's properties: the
        packed record as a NumPy dtype description (``[("x", "<f4"), ...]``)."""
        return [(p.name, self.byte_order + PLY_SCALARS[p.kind].code) for p in element.properties]


def read_ply_header(head: bytes, where: str = "file", *, code: str = CODE_INVALID) -> PlyHeader:
    """The header at the start of ``head`` (a file's first bytes, up to
    :data:`HEADER_MAX_BYTES`). FormatError ``code`` when the first line is not ``ply``,
    there is no ``end_header`` line (with its line end), the format is unknown, an element
    has no whole-number count, a property line is malformed or names an unknown type."""
    first = head.split(b"\n", 1)[0].strip()
    if first != b"ply":
        raise FormatError(where, "not a PLY file (its first line is not 'ply')", code=code)
    end = head.find(b"end_header")
    if end < 0:
        raise FormatError(where, "the PLY header has no 'end_header' line", code=code)
    newline = head.find(b"\n", end)
    if newline < 0:
        raise FormatError(where, "the PLY header's 'end_header' has no line end", code=code)
    fmt = version = ""
    elements: list[tuple[str, int, list[PlyProperty]]] = []
    for line in head[:end].decode("latin-1").splitlines()[1:]:
        words = line.split()
        if words[:1] == ["format"] and len(words) >= 2:
            fmt, version = words[1], (words[2] if len(words) >= 3 else "")
        elif words[:1] == ["element"] and len(words) == 3:
            if not (words[2].isascii() and words[2].isdigit()):
                raise FormatError(where, f"element {show(words[1])} has no count", code=code)
            elements.append((words[1], int(words[2]), []))
        elif words[:1] == ["property"] and elements:
            elements[-1][2].append(_property(words, line, where, code))
        elif words[:1] in (["element"], ["property"]):  # a short element, an orphan property
            raise FormatError(where, f"cannot read the header line {show(line)}", code=code)
    if fmt not in FORMATS:
        raise FormatError(where, f"unknown PLY format {show(fmt)}", code=code)
    found = tuple(PlyElement(n, c, tuple(p)) for n, c, p in elements)
    return PlyHeader(fmt, version, found, newline + 1)


def _property(words: list[str], line: str, where: str, code: str) -> PlyProperty:
    """One ``property`` line: ``property TYPE NAME`` or ``property list COUNT TYPE NAME``."""
    if words[1:2] == ["list"] and len(words) == 5:
        prop = PlyProperty(words[4], words[3], words[2])
    elif len(words) == 3 and words[1] != "list":
        prop = PlyProperty(words[2], words[1])
    else:
        raise FormatError(where, f"cannot read the header line {show(line)}", code=code)
    for kind in (prop.count_kind, prop.kind):
        if kind is not None and kind not in PLY_SCALARS:
            raise FormatError(where, f"unknown PLY property type {show(kind)}", code=code)
    return prop


def ply_body_problem(header: PlyHeader, size_bytes: int) -> str | None:
    """Why a file of ``size_bytes`` cannot hold the elements ``header`` declares, or None.
    Each element needs at least ``count ×`` its values' :meth:`PlyProperty.min_bytes`."""
    body = size_bytes - header.header_bytes
    for element in header.elements:
        need = element.count * sum(p.min_bytes(header.binary) for p in element.properties)
        if need > body:
            return (
                f"the PLY header declares {element.count} {element.name} elements, which need "
                f"at least {need} bytes, but the file holds {body} after its header"
            )
    return None


def ply_count_problem(head: bytes, size_bytes: int) -> str | None:
    """Why the header at the start of ``head`` is not one (:func:`read_ply_header`) or
    promises more than a file of ``size_bytes`` holds (:func:`ply_body_problem`), or None."""
    try:
        header = read_ply_header(head)
    except FormatError as exc:
        return exc.problem
    return ply_body_problem(header, size_bytes)


def read_ply_file_header(
    path: Path, where: str | None = None, *, code: str = CODE_INVALID
) -> PlyHeader:
    """The header of the PLY file at ``path`` (``where`` in messages: its name unless
    given), its counts checked against the file's size; FormatError ``code`` otherwise."""
    where = path.name if where is None else where
    size = path.stat().st_size
    with path.open("rb") as fh:
        head = fh.read(HEADER_MAX_BYTES)
    header = read_ply_header(head, where, code=code)
    problem = ply_body_problem(header, size)
    if problem is not None:
        raise FormatError(where, problem, code=code)
    return header


def vertex_element(
    header: PlyHeader, where: str = "file", *, code: str = CODE_INVALID
) -> PlyElement:
    """The leading ``vertex`` element of a point cloud or model, which every PLY reader here
    reads as packed records. FormatError ``code`` when there is none with ``x y z``, it is
    not the first element, or it has a list property."""
    vertex = header.element("vertex")
    if vertex is None or not {"x", "y", "z"} <= {p.name for p in vertex.properties}:
        raise FormatError(where, "no vertex element with x, y and z", code=code)
    if header.elements[0] is not vertex:
        raise FormatError(where, "the vertex element must come first", code=code)
    if not vertex.scalar_only:
        raise FormatError(where, "list properties in 'vertex' are not supported", code=code)
    return vertex
