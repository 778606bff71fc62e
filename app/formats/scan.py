"""Laser scans: which format a file is (by its magic bytes), what its header promises, and
the ``frame`` document that says how its coordinates map into the environment frame. One
reader of each, used by the API (``POST /v1/environments/{id}/scans``, headers only) and by
the worker that reads the points. Standard library only.

Formats:

- **E57** (ASTM E2807): starts ``ASTM-E57``; read with pye57 (not here).
- **LAS / LAZ**: starts ``LASF``; LAZ sets bit 7 of the point format id. Header fields are
  read here (:func:`read_las_header`).
- **PLY**: starts ``ply``; the ``vertex`` element must come first and carry ``x y z``
  (optional ``red green blue``, ``intensity``), no list properties
  (:func:`app.formats.ply.read_ply_header` and :func:`app.formats.ply.vertex_element`).

The frame document (multipart field ``frame``)::

    {"transform": 4×4, "units": "m"}   # env_from_scan: rigid, row-major, metres
    {"markers": true, "units": "mm"}   # the environment's marker sheet, found in the scan

``units`` (default ``m``) is the unit of the coordinates as stored (after E57 poses, LAS
scale and offset): ``m``, ``cm``, ``mm``, ``ft`` (international foot), ``us_ft`` (US survey
foot) or ``in``; points are scaled to metres before the transform. Errors are
:class:`~app.formats.errors.FormatError` naming the problem.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass
from typing import Any, Literal

from app.formats.cameras import Pose, check_rigid
from app.formats.errors import FormatError, show

ScanFormat = Literal["e57", "las", "laz", "ply"]
FrameMethod = Literal["transform", "markers"]

# Metres per unit of the stored coordinates.
UNITS_M = {
    "m": 1.0,
    "cm": 0.01,
    "mm": 0.001,
    "ft": 0.3048,
    "us_ft": 1200.0 / 3937.0,
    "in": 0.0254,
}
SNIFF_BYTES = 512  # enough for every magic below and a LAS 1.4 header's point count
FRAME_MAX_BYTES = 16 * 1024

CODE_TRUNCATED = "TruncatedScan"
CODE_EMPTY = "EmptyScan"
CODE_INVALID = "InvalidScan"
CODE_FRAME = "InvalidFrame"


def sniff_scan_format(head: bytes) -> ScanFormat | None:
    """The scan format of a file starting with ``head`` (its first bytes), or None."""
    if head.startswith(b"ASTM-E57"):
        return "e57"
    if head.startswith(b"LASF") and len(head) > 104:
        return "laz" if head[104] & 0x80 else "las"
    if head.startswith((b"ply\n", b"ply\r\n")):
        return "ply"
    return None


@dataclass(frozen=True)
class LasHeader:
    """The fields of a LAS/LAZ public header block that size its points."""

    version: tuple[int, int]
    offset_to_points: int
    point_format: int  # without the compression bits
    record_length: int  # bytes per point, uncompressed
    point_count: int
    compressed: bool


def read_las_header(head: bytes, where: str = "scan") -> LasHeader:
    """The public header block at the start of ``head`` (≥ 375 bytes for LAS 1.4 counts).
    FormatError ``InvalidScan`` when it is not one."""
    if not head.startswith(b"LASF") or len(head) < 227:
        raise FormatError(where, "not a LAS file (no 227-byte LASF header)", code=CODE_INVALID)
    major, minor = head[24], head[25]
    header_size, offset = struct.unpack_from("<HI", head, 94)
    fmt_id, record_length, legacy_count = struct.unpack_from("<BHI", head, 104)
    count = legacy_count
    if (major, minor) >= (1, 4) and header_size >= 255 and len(head) >= 255:
        count = struct.unpack_from("<Q", head, 247)[0] or legacy_count
    if offset < header_size or record_length == 0:
        raise FormatError(
            where, f"LAS header: offset to points {offset}, record length {record_length}",
            code=CODE_INVALID,
        )  # fmt: skip
    return LasHeader(
        version=(major, minor),
        offset_to_points=offset,
        point_format=fmt_id & 0x3F,
        record_length=record_length,
        point_count=count,
        compressed=bool(fmt_id & 0x80),
    )


def las_size_problem(header: LasHeader, size_bytes: int, chunk_table_at: int | None) -> str | None:
    """Why a LAS/LAZ file of ``size_bytes`` cannot hold what ``header`` promises, or None.

    LAS: the points need ``offset + count × record length`` bytes. LAZ: the chunk table
    offset (``chunk_table_at``, the int64 at the start of the point data; -1 when the writer
    did not record it) must lie inside the file, which a cut-off file's does not."""
    if not header.compressed:
        need = header.offset_to_points + header.point_count * header.record_length
        if need > size_bytes:
            return (
                f"the LAS header declares {header.point_count} points of "
                f"{header.record_length} bytes ({need} bytes with the header) but the file "
                f"holds {size_bytes}: it is truncated"
            )
        return None
    if header.offset_to_points + 8 > size_bytes:
        return f"the LAZ file ends ({size_bytes} bytes) before its point data: it is truncated"
    recorded = chunk_table_at is not None and chunk_table_at != -1
    if recorded and not header.offset_to_points + 8 <= (chunk_table_at or 0) <= size_bytes - 8:
        return (
            f"the LAZ chunk table is at byte {chunk_table_at} but the file holds "
            f"{size_bytes}: it is truncated"
        )
    return None


@dataclass(frozen=True)
class ScanFrame:
    """How a scan's coordinates reach the environment frame: ``method`` ``transform``
    (``env_from_scan``, 4×4 rigid, metres) or ``markers`` (the environment's marker sheet
    found in the scan), after scaling the stored coordinates by ``metres_per_unit``."""

    method: FrameMethod
    env_from_scan: Pose | None
    units: str

    @property
    def metres_per_unit(self) -> float:
        return UNITS_M[self.units]

    def to_json(self) -> dict[str, Any]:
        """The normalised frame document."""
        if self.method == "markers":
            return {"markers": True, "units": self.units}
        assert self.env_from_scan is not None
        return {"transform": [list(row) for row in self.env_from_scan], "units": self.units}


def read_scan_frame(doc: Any, where: str = "frame") -> ScanFrame:
    """Check a parsed frame document (above); FormatError ``InvalidFrame`` naming the field:
    neither or both of ``transform`` and ``markers``, a transform that is not a 4×4 rigid
    matrix of finite numbers (rotation within 1e-6), an unknown unit or key."""
    if not isinstance(doc, dict):
        raise FormatError(
            where, 'expected {"transform": 4×4} or {"markers": true}', code=CODE_FRAME
        )
    unknown = set(doc) - {"transform", "markers", "units"}
    if unknown:
        raise FormatError(where, f"unknown field {show(sorted(unknown)[0])}", code=CODE_FRAME)
    units = doc.get("units", "m")
    if not isinstance(units, str) or units not in UNITS_M:
        raise FormatError(
            f"{where}.units", f"{show(units)} is not one of {', '.join(UNITS_M)}", code=CODE_FRAME
        )
    has_transform = doc.get("transform") is not None
    markers = doc.get("markers", False)
    if not isinstance(markers, bool):
        raise FormatError(f"{where}.markers", "expected true or false", code=CODE_FRAME)
    if has_transform == markers:
        raise FormatError(
            where, 'give exactly one of "transform" (4×4) and "markers": true', code=CODE_FRAME
        )
    if markers:
        return ScanFrame("markers", None, units)
    pose = check_rigid(doc["transform"], f"{where}.transform", code=CODE_FRAME)
    return ScanFrame("transform", pose, units)


def parse_scan_frame(text: str | bytes, where: str = "frame") -> ScanFrame:
    """:func:`read_scan_frame` of a JSON text (at most 16 KiB; NaN and Infinity refused)."""
    if len(text) > FRAME_MAX_BYTES:
        raise FormatError(where, f"longer than {FRAME_MAX_BYTES} bytes", code=CODE_FRAME)

    def constant(name: str) -> Any:
        raise ValueError(f"{name} is not a number in JSON")

    try:
        doc = json.loads(text, parse_constant=constant)
    except (ValueError, RecursionError) as exc:
        raise FormatError(where, f"not JSON ({exc})", code=CODE_FRAME) from exc
    return read_scan_frame(doc, where)
