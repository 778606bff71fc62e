"""Laser scans as snapshots: stream an uploaded E57, LAS, LAZ or PLY file into staging, check
its header (cheap: never its points), insert a snapshot with ``source = scan`` and queue the
same ``snapshot.process`` job a photo capture gets; the worker reads the points.

Stored under the snapshot's prefix::

    snapshots/<id>/scan/scan.<e57|las|laz|ply>   the file as uploaded
    snapshots/<id>/scan.json                     format, file, frame, points_declared, bytes

The format is recognised by its magic bytes (415 otherwise). A truncated file, one without
points, or an unusable ``frame`` is a 422 naming the problem; nothing is kept on any error.
The same ``Idempotency-Key`` with the same file and frame returns the first snapshot.
"""

from __future__ import annotations

import hashlib
import json
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import pye57
from sqlalchemy.orm import Session, sessionmaker

from app.core import environments
from app.core.enums import SnapshotSource
from app.core.errors import UnsupportedMedia
from app.core.ingest.common import (
    _disk_full,
    _invalid,
    _no_space,
    _reason,
    _too_large,
)
from app.core.ingest.staging import _staging_dir, sweep_staging
from app.core.ingest.upload import Ingested, _reading, insert_snapshot, replay_of
from app.core.models import Environment
from app.core.settings import Settings
from app.core.storage import CHUNK_BYTES, Storage
from app.formats import FormatError
from app.formats.ply import HEADER_MAX_BYTES, ply_body_problem, read_ply_header, vertex_element
from app.formats.scan import (
    CODE_EMPTY,
    CODE_INVALID,
    CODE_TRUNCATED,
    SNIFF_BYTES,
    ScanFormat,
    ScanFrame,
    las_size_problem,
    parse_scan_frame,
    read_las_header,
    sniff_scan_format,
)

RECORD_NAME = "scan.json"


@dataclass(frozen=True)
class ScanRecord:
    """What ``scan.json`` says: the stored file's format and key, the frame, the point count
    its header declares and its size in bytes."""

    format: ScanFormat
    file_key: str
    frame: ScanFrame
    points_declared: int
    size_bytes: int


def load_record(storage: Storage, prefix: str) -> ScanRecord:
    """The ``scan.json`` of the scan snapshot stored under ``prefix``."""
    doc = json.loads(storage.local_file(f"{prefix}/{RECORD_NAME}").read_text())
    return ScanRecord(
        format=doc["format"],
        file_key=f"{prefix}/{doc['file']}",
        frame=parse_scan_frame(json.dumps(doc["frame"])),
        points_declared=int(doc["points_declared"]),
        size_bytes=int(doc["bytes"]),
    )


@dataclass
class _StagedScan:
    path: Path
    format: ScanFormat
    size: int
    sha256: str


def _stream_in(source: BinaryIO, root: Path, max_bytes: int) -> _StagedScan:
    """Copy the upload into ``root/scan/`` in chunks (never whole), recognising its format
    from the first bytes: 415 ``UnsupportedFileType`` for none of E57/LAS/LAZ/PLY (before
    the rest is read), 413 past ``max_bytes``, 507 on a full disk."""
    target = root / "scan" / "upload.part"
    digest = hashlib.sha256()
    size = 0
    head = b""
    fmt: ScanFormat | None = None
    try:
        target.parent.mkdir(parents=True)
        with target.open("wb") as out:
            while chunk := source.read(CHUNK_BYTES):
                if fmt is None:
                    head += chunk
                    if len(head) < SNIFF_BYTES and (more := source.read(SNIFF_BYTES)):
                        head += more  # a short first read: sniff on enough bytes
                    fmt = sniff_scan_format(head)
                    if fmt is None:
                        raise UnsupportedMedia(
                            "file: not an E57, LAS, LAZ or PLY point cloud (recognised by "
                            "content: ASTM-E57, LASF or ply at the start)",
                            code="UnsupportedFileType",
                        )
                    chunk = head
                size += len(chunk)
                if size > max_bytes:
                    raise _too_large(
                        "PayloadTooLarge", f"file: larger than {max_bytes} bytes (max_scan_bytes)"
                    )
                digest.update(chunk)
                out.write(chunk)
    except OSError as exc:
        if _disk_full(exc):
            raise _no_space("file") from exc
        raise
    if fmt is None:
        raise _invalid(CODE_EMPTY, "file: the upload is empty")
    final = target.with_name(f"scan.{fmt}")
    target.rename(final)
    return _StagedScan(final, fmt, size, digest.hexdigest())


def _e57_points(path: Path) -> int:
    """Points an E57 file declares over all its scans (opening checks the file's length
    and its XML section's page checksums)."""
    try:
        with pye57.E57(str(path)) as e57:
            total = 0
            for index in range(e57.scan_count):
                header = e57.get_header(index)
                fields = set(header.point_fields)
                if not (
                    {"cartesianX", "cartesianY", "cartesianZ"} <= fields
                    or {"sphericalRange", "sphericalAzimuth", "sphericalElevation"} <= fields
                ):
                    raise _invalid(CODE_INVALID, f"file: E57 scan {index} has no coordinates")
                total += int(header.point_count)
            return total
    except pye57.libe57.E57Exception as exc:
        text = _reason(Exception(str(exc).strip().splitlines()[0] if str(exc).strip() else exc))
        if "BadFileLength" in text or "BadChecksum" in text:
            raise _invalid(
                CODE_TRUNCATED, f"file: the E57 file is truncated or damaged ({text})"
            ) from exc
        raise _invalid(CODE_INVALID, f"file: not a readable E57 file ({text})") from exc


def check_header(path: Path, fmt: ScanFormat, size: int) -> int:
    """The point count the file's header declares, after checking that the file can hold
    them; 422 ``TruncatedScan``, ``EmptyScan`` (no points) or ``InvalidScan``. Reads the
    header only."""
    try:
        if fmt == "e57":
            count = _e57_points(path)
        elif fmt in ("las", "laz"):
            with path.open("rb") as fh:
                head = fh.read(SNIFF_BYTES)
                header = read_las_header(head, "file")
                fh.seek(header.offset_to_points)
                raw = fh.read(8)
            table = struct.unpack("<q", raw)[0] if header.compressed and len(raw) == 8 else None
            problem = las_size_problem(header, size, table)
            if problem:
                raise _invalid(CODE_TRUNCATED, f"file: {problem}")
            count = header.point_count
        else:
            with path.open("rb") as fh:
                ply = read_ply_header(fh.read(HEADER_MAX_BYTES), "file", code=CODE_INVALID)
            count = vertex_element(ply, "file", code=CODE_INVALID).count
            problem = ply_body_problem(ply, size)
            if problem:
                raise _invalid(CODE_TRUNCATED, f"file: {problem}")
    except FormatError as exc:
        raise _invalid(exc.code, exc.detail) from exc
    if count == 0:
        raise _invalid(CODE_EMPTY, f"file: the {fmt.upper()} file holds no points")
    return count


def _frame(text: str | None, env: Environment) -> ScanFrame:
    """The checked ``frame`` field; 422 ``InvalidFrame``, or ``NoMarkerSheet`` when it asks
    for markers and the environment has none."""
    if text is None:
        raise _invalid(
            "InvalidFrame", 'frame: missing; give {"transform": 4×4} or {"markers": true}'
        )
    try:
        frame = parse_scan_frame(text)
    except FormatError as exc:
        raise _invalid(exc.code, exc.detail) from exc
    if frame.method == "markers" and not (env.reference or {}).get("markers"):
        raise _invalid(
            "NoMarkerSheet",
            f"frame: markers asked for, but environment {env.id} has no marker sheet "
            "(reference.markers); give a transform instead",
        )
    return frame


def create_scan_snapshot(
    session: Session,
    storage: Storage,
    settings: Settings,
    environment_id: str,
    source: BinaryIO,
    frame_text: str | None,
    *,
    idempotency_key: str | None = None,
    lookup: sessionmaker[Session] | None = None,
) -> Ingested:
    """Store an uploaded scan and queue its job (see the module's docstring). ``lookup``
    opens short read sessions as in :func:`app.core.ingest.create_snapshot`, so ``session``
    writes only the insert."""
    with _reading(session, lookup) as reader:
        env = environments.get(reader, environment_id)
        frame = _frame(frame_text, env)
        env_id = env.id
    if idempotency_key is not None and not 0 < len(idempotency_key) <= 200:
        raise _invalid("InvalidUpload", "Idempotency-Key: 1 to 200 characters")
    sweep_staging(storage)
    with _staging_dir(storage) as root:
        staged = _stream_in(source, root, settings.max_scan_bytes)
        frame_json = json.dumps(frame.to_json(), sort_keys=True)
        digest = hashlib.sha256(f"scan\0{staged.sha256}\0{frame_json}".encode()).hexdigest()
        replay = replay_of(session, lookup, env_id, idempotency_key, digest)
        if replay is not None:
            return replay
        count = check_header(staged.path, staged.format, staged.size)
        record = {
            "format": staged.format,
            "file": f"scan/{staged.path.name}",
            "frame": frame.to_json(),
            "points_declared": count,
            "bytes": staged.size,
        }
        (root / RECORD_NAME).write_text(json.dumps(record))
        return insert_snapshot(
            session, storage, env_id, root, _scan_fields(staged.size), idempotency_key, digest
        )


def _scan_fields(size: int) -> dict[str, Any]:
    """A scan snapshot's columns: one file of ``size`` bytes, no images or cameras."""
    return {
        "source": SnapshotSource.scan,
        "n_images": 0,
        "n_detections": 0,
        "upload_bytes": size,
        "has_cameras": False,
    }
