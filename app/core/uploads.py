"""Resumable uploads (tus 1.0: core, creation, termination, checksum, expiration) of one
capture archive (.zip, .tar, .tar.gz), for capture stations on connections that drop.

An upload is a row (:class:`~app.core.models.ResumableUpload`: offset, length, metadata,
owner) and its bytes as stored parts, one per PATCH: ``uploads/<id>/<start:020d>.<nonce>``
through :class:`~app.core.storage.Storage`, so any API host can take the next PATCH (with S3
storage the hosts share only the database and the bucket). A PATCH spools its body to this
host's scratch, stores it as a part, then moves the row's offset in one locked transaction
only if it still is the PATCH's start: of two PATCHes at one offset, on any hosts, the
second gets 409 and its part is deleted. A request killed mid-body stored nothing the row
names; bytes that arrived before a connection dropped are kept (unless the chunk carried a
checksum, which they could not match). When the last byte is in, one request claims the
upload (``processing``, kept alive by a heartbeat; another request answers 423 meanwhile,
or takes over once the heartbeat is :data:`FINISH_STALE_S` old) and reads the parts in
order as one archive through the same ingest as a single-request archive upload
(:func:`app.core.ingest.create_snapshot`: the same checks, errors and ``Idempotency-Key``
semantics); the snapshot and its job are recorded on the upload in the same transaction,
and the parts go once that commits. A refused archive keeps its error on the row and loses
its bytes.

Every write moves ``expires_at`` to ``upload_expiry_s`` from now; :func:`expire` (beat's
``maintenance.uploads``) deletes expired uploads with their parts, part folders without a
row, and spooled or half-stored parts that killed requests left.
"""

from __future__ import annotations

import base64
import binascii
import bisect
import hashlib
import io
import logging
import os
import re
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime, timedelta
from io import RawIOBase
from pathlib import Path
from typing import Any, BinaryIO, cast

from sqlalchemy import delete, select, update
from sqlalchemy.orm import Session, sessionmaker

from app.core import environments, ingest, retention
from app.core.enums import UploadState
from app.core.errors import (
    Conflict,
    DomainError,
    InvalidInput,
    NotFound,
    PayloadTooLarge,
    UnsupportedMedia,
)
from app.core.ingest.common import _disk_full, _no_space
from app.core.models import ResumableUpload, new_id, utcnow
from app.core.settings import Settings
from app.core.storage import CHUNK_BYTES, Storage, remove_older

log = logging.getLogger(__name__)

TUS_VERSION = "1.0.0"
TUS_EXTENSIONS = "creation,termination,checksum,expiration"
# Upload-Checksum algorithms (tus names), each a hashlib constructor.
CHECKSUMS: dict[str, Callable[[], Any]] = {
    "sha1": hashlib.sha1,
    "sha256": hashlib.sha256,
    "sha512": hashlib.sha512,
    "md5": hashlib.md5,
}
ARCHIVE_SUFFIXES = (".zip", ".tar", ".tar.gz", ".tgz")
FOLDER = "uploads"
FINISH_BEAT_S = 5.0  # a request ingesting an upload writes its heartbeat this often
FINISH_STALE_S = 30.0  # another request may take over once the heartbeat is this old
_SHA256 = re.compile(r"^[0-9a-f]{64}$")


class BadRequest(DomainError):
    """400: a tus header is missing or malformed."""

    status_code = 400
    code = "BadRequest"


class UploadLocked(DomainError):
    """423: another request is ingesting this upload's archive; retry after a short wait."""

    status_code = 423
    code = "UploadLocked"


class ChecksumMismatch(DomainError):
    """460 (tus checksum extension): the chunk's bytes do not match its Upload-Checksum;
    the chunk was discarded."""

    status_code = 460
    code = "ChecksumMismatch"


# --- headers --------------------------------------------------------------------------------


def parse_metadata(header: str | None) -> dict[str, str]:
    """``Upload-Metadata``: comma-separated ``key base64(value)`` pairs (the value may be
    left out); 400 naming the pair that is not."""
    result: dict[str, str] = {}
    for pair in (header or "").split(","):
        if not pair.strip():
            continue
        key, _, value = pair.strip().partition(" ")
        try:
            decoded = base64.b64decode(value.strip(), validate=True).decode() if value else ""
        except (binascii.Error, UnicodeDecodeError) as exc:
            raise BadRequest(
                f"Upload-Metadata: the value of {key!r} is not base64 of UTF-8 text",
                code="InvalidUploadMetadata",
            ) from exc
        if key in result:
            raise BadRequest(f"Upload-Metadata: {key!r} given twice", code="InvalidUploadMetadata")
        result[key] = decoded
    return result


def parse_checksum(header: str | None) -> tuple[str, bytes] | None:
    """``Upload-Checksum: <algorithm> <base64 digest>`` → (algorithm, digest); 400 for an
    algorithm not in :data:`CHECKSUMS` or a digest that is not base64."""
    if header is None:
        return None
    algorithm, _, encoded = header.strip().partition(" ")
    if algorithm.lower() not in CHECKSUMS:
        raise BadRequest(
            f"Upload-Checksum: unsupported algorithm {algorithm!r} "
            f"(supported: {', '.join(CHECKSUMS)})",
            code="UnsupportedChecksumAlgorithm",
        )
    try:
        digest = base64.b64decode(encoded.strip(), validate=True)
    except binascii.Error as exc:
        raise BadRequest(
            "Upload-Checksum: the digest is not base64", code="InvalidChecksum"
        ) from exc
    return algorithm.lower(), digest


def parse_offset(header: str | None, name: str = "Upload-Offset") -> int:
    """A non-negative integer header; 400 when it is missing or not one."""
    if header is None or not header.strip().isdigit():
        raise BadRequest(f"{name}: a non-negative integer is required", code=f"Invalid{name}")
    return int(header.strip())


# --- rows -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class NewUpload:
    """What a creation request declares: ``length`` bytes of archive ``filename`` for
    ``environment_id``; optional ``idempotency_key`` and the archive's ``sha256`` (hex)."""

    environment_id: str
    length: int
    filename: str
    idempotency_key: str | None = None
    sha256: str | None = None

    @classmethod
    def from_headers(cls, length_header: str | None, metadata_header: str | None) -> NewUpload:
        """From ``Upload-Length`` and ``Upload-Metadata`` (``environment_id``,
        ``filename``, optional ``idempotency_key``, ``sha256``); 400/422 naming the field."""
        length = parse_offset(length_header, "Upload-Length")
        meta = parse_metadata(metadata_header)
        for required in ("environment_id", "filename"):
            if not meta.get(required):
                raise InvalidInput(
                    f"Upload-Metadata: {required!r} is required", code="InvalidUploadMetadata"
                )
        sha = meta.get("sha256") or None
        return cls(
            environment_id=meta["environment_id"],
            length=length,
            filename=meta["filename"],
            idempotency_key=meta.get("idempotency_key") or None,
            sha256=sha.lower() if sha else None,
        )


def _check_new(new: NewUpload, settings: Settings) -> None:
    if new.length == 0:
        raise InvalidInput("Upload-Length: an empty upload holds no capture", code="InvalidInput")
    if new.length > settings.max_upload_bytes:
        raise PayloadTooLarge(
            f"Upload-Length {new.length} is larger than max_upload_bytes "
            f"({settings.max_upload_bytes})"
        )
    name = new.filename.replace("\\", "/").rsplit("/", 1)[-1]
    if not name or len(new.filename) > 255 or not name.lower().endswith(ARCHIVE_SUFFIXES):
        raise UnsupportedMedia(
            f"{new.filename!r}: a resumable upload is one archive, .zip, .tar or .tar.gz",
            code="UnsupportedFileType",
        )
    if new.idempotency_key is not None and len(new.idempotency_key) > 200:
        raise InvalidInput("idempotency_key: 1 to 200 characters", code="InvalidUpload")
    if new.sha256 is not None and not _SHA256.match(new.sha256):
        raise InvalidInput("sha256: 64 hexadecimal digits", code="InvalidUploadMetadata")


def create(session: Session, settings: Settings, new: NewUpload) -> tuple[ResumableUpload, bool]:
    """A new upload with no bytes yet, or the unexpired upload that already has this
    ``idempotency_key``, ``sha256`` and length (so a client that lost its upload URL resumes
    instead of sending everything again); returns (upload, created).

    404 for an unknown environment; 413 beyond ``max_upload_bytes``; 415 for a name that is
    not an archive."""
    environments.get(session, new.environment_id)
    _check_new(new, settings)
    if new.idempotency_key is not None and new.sha256 is not None:
        earlier = session.scalars(
            select(ResumableUpload)
            .where(
                ResumableUpload.environment_id == new.environment_id,
                ResumableUpload.idempotency_key == new.idempotency_key,
                ResumableUpload.sha256 == new.sha256,
                ResumableUpload.length == new.length,
                ResumableUpload.state != UploadState.failed,
                ResumableUpload.expires_at > utcnow(),
            )
            .order_by(ResumableUpload.created_at.desc())
        ).first()
        if earlier is not None:
            return earlier, False
    upload_id = new_id()
    upload = ResumableUpload(
        id=upload_id,
        environment_id=new.environment_id,
        state=UploadState.receiving,
        length=new.length,
        filename=new.filename,
        idempotency_key=new.idempotency_key,
        sha256=new.sha256,
        storage_key=f"{FOLDER}/{upload_id}",
        offset_bytes=0,
        parts=[],
        expires_at=utcnow() + timedelta(seconds=settings.upload_expiry_s),
    )
    session.add(upload)
    session.flush()
    return upload, True


def get(session: Session, upload_id: str, now: datetime | None = None) -> ResumableUpload:
    """The upload; 404 ``NotFound`` for an unknown id, ``UploadExpired`` past its expiry."""
    upload = session.get(ResumableUpload, upload_id)
    if upload is None:
        raise NotFound(f"upload {upload_id} not found")
    if upload.expires_at <= (now or utcnow()):
        raise NotFound(f"upload {upload_id} expired at {upload.expires_at:%Y-%m-%dT%H:%M:%SZ}",
                       code="UploadExpired")  # fmt: skip
    return upload


def offset(upload: ResumableUpload) -> int:
    """Bytes received: the stored parts' total while receiving, the length afterwards."""
    return upload.offset_bytes if upload.state == UploadState.receiving else upload.length


def check_offset(upload: ResumableUpload, start: int) -> None:
    """409 ``OffsetMismatch`` unless a PATCH's Upload-Offset ``start`` is the upload's."""
    if start != offset(upload):
        raise Conflict(
            f"Upload-Offset {start} is not the upload's offset {offset(upload)}: HEAD it and "
            "resume from there",
            code="OffsetMismatch",
        )


def _alive(upload: ResumableUpload, now: datetime) -> bool:
    """Whether a ``processing`` upload's finishing request beat within FINISH_STALE_S."""
    return (
        upload.state == UploadState.processing
        and upload.heartbeat_at is not None
        and upload.heartbeat_at > now - timedelta(seconds=FINISH_STALE_S)
    )


def _being_ingested(upload_id: str) -> UploadLocked:
    return UploadLocked(f"upload {upload_id}: its archive is being ingested; retry in a moment")


# --- writing --------------------------------------------------------------------------------


class Receiver:
    """One PATCH's bytes: spooled to ``<storage_key>/.<part>.part`` in this host's scratch
    between :meth:`open` and :meth:`close`, then stored as the upload's next part
    (:meth:`store`).

    ``start`` is the request's Upload-Offset, the most the chunk may carry is what is left
    of Upload-Length from there (413 past it), ``checksum`` the chunk's Upload-Checksum (460
    and the chunk discarded when it does not match)."""

    def __init__(
        self,
        storage: Storage,
        upload: ResumableUpload,
        start: int,
        checksum: tuple[str, bytes] | None,
    ) -> None:
        self.storage, self.upload_id, self.start = storage, upload.id, start
        self.limit = max(upload.length - start, 0)
        self.name = f"{start:020d}.{uuid.uuid4().hex[:16]}"
        self.key = f"{upload.storage_key}/{self.name}"
        self.path = storage.scratch_path(f"{upload.storage_key}/.{self.name}.part")
        self.checksum = checksum
        self.hasher = CHECKSUMS[checksum[0]]() if checksum else None
        self.written = 0
        self._fh: BinaryIO | None = None

    def open(self) -> None:
        """Create the spool file; 507 on a full disk."""
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._fh = self.path.open("wb")
        except OSError as exc:
            if _disk_full(exc):
                raise _no_space(f"upload {self.upload_id}") from exc
            raise

    @property
    def fh(self) -> BinaryIO:
        if self._fh is None:
            raise RuntimeError("Receiver.open() first")
        return self._fh

    def write(self, data: bytes | bytearray) -> None:
        """Append ``data``; 413 past the limit, 507 on a full disk (either discards the chunk)."""
        if self.written + len(data) > self.limit:
            self.rollback()
            raise PayloadTooLarge(
                f"upload {self.upload_id}: the chunk runs past Upload-Length "
                f"({self.limit} bytes were left from offset {self.start})"
            )
        try:
            self.fh.write(data)
        except OSError as exc:
            self.rollback()
            if _disk_full(exc):
                raise _no_space(f"upload {self.upload_id}") from exc
            raise
        if self.hasher is not None:
            self.hasher.update(data)
        self.written += len(data)

    def commit(self) -> int:
        """Keep what was written (460 and nothing kept when the checksum does not match);
        returns the bytes kept."""
        if (
            self.checksum is not None
            and self.hasher is not None
            and self.hasher.digest() != self.checksum[1]
        ):
            self.rollback()
            raise ChecksumMismatch(
                f"upload {self.upload_id}: the chunk's {self.checksum[0]} does not match "
                "Upload-Checksum; it was discarded, send it again"
            )
        return self.written

    def keep_partial(self) -> int:
        """After a dropped connection: keep the bytes that arrived, unless the chunk has a
        checksum (they cannot be verified); returns the bytes kept."""
        if self.checksum is not None:
            self.rollback()
        return self.written

    def rollback(self) -> None:
        """Discard this chunk."""
        self.fh.seek(0)
        self.fh.truncate()
        self.written = 0

    def store(self, factory: sessionmaker[Session], settings: Settings) -> ResumableUpload:
        """Store the bytes kept as the upload's next part, and move its offset past them
        and its expiry to ``upload_expiry_s`` from now in one transaction with the row
        locked; returns the row. Nothing kept: only the expiry moves.

        409 ``OffsetMismatch`` when another request moved the offset first (or ended the
        upload), 404 when the upload is gone: either way the part is deleted. 507 when the
        storage is full."""
        self._close_file()
        expires_at = utcnow() + timedelta(seconds=settings.upload_expiry_s)
        if self.written:
            try:
                self.storage.move_in(self.path, self.key)
            except OSError as exc:
                if _disk_full(exc):
                    raise _no_space(f"upload {self.upload_id}") from exc
                raise
        try:
            with factory.begin() as session:
                row = session.get(ResumableUpload, self.upload_id, with_for_update=True)
                if row is None or row.expires_at <= utcnow():
                    raise NotFound(f"upload {self.upload_id} is gone", code="UploadExpired")
                if self.written:
                    check_offset(row, self.start)
                    row.parts = [*row.parts, self.name]
                    row.offset_bytes = self.start + self.written
                row.expires_at = expires_at
        except BaseException:
            if self.written:
                self._delete_part()
            raise
        return row

    def _delete_part(self) -> None:
        try:
            self.storage.delete_prefix(self.key)
        except OSError:  # left under the upload's prefix: deleted with the upload
            log.exception("could not delete the refused part %s", self.key)

    def _close_file(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None

    def close(self) -> None:
        """Close and remove the spool file (once stored it is gone already)."""
        self._close_file()
        self.path.unlink(missing_ok=True)


# --- the end of an upload -------------------------------------------------------------------


class _Joined(RawIOBase):
    """Files read one after another as one seekable stream (an upload's parts in order)."""

    def __init__(self, paths: list[Path]) -> None:
        self.paths = paths
        self.starts = [0]
        for path in paths:
            self.starts.append(self.starts[-1] + path.stat().st_size)
        self.pos = 0
        self._index = -1
        self._fh: BinaryIO | None = None

    @property
    def size(self) -> int:
        return self.starts[-1]

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def tell(self) -> int:
        return self.pos

    def seek(self, offset: int, whence: int = os.SEEK_SET) -> int:
        base = {os.SEEK_SET: 0, os.SEEK_CUR: self.pos, os.SEEK_END: self.size}[whence]
        if base + offset < 0:
            raise ValueError(f"negative seek position {base + offset}")
        self.pos = base + offset
        return self.pos

    def readinto(self, buffer: Any) -> int:
        if self.pos >= self.size:
            return 0
        index = bisect.bisect_right(self.starts, self.pos) - 1
        if index != self._index:
            if self._fh is not None:
                self._fh.close()
            self._fh, self._index = self.paths[index].open("rb"), index
        fh = cast(BinaryIO, self._fh)
        fh.seek(self.pos - self.starts[index])
        view = memoryview(buffer)[: self.starts[index + 1] - self.pos]
        n = fh.readinto(view)  # type: ignore[attr-defined]
        self.pos += n
        return int(n)

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None
        super().close()


@contextmanager
def _archive(storage: Storage, upload: ResumableUpload) -> Iterator[BinaryIO]:
    """The upload's parts in order as one seekable file (local copies on this host: the
    parts themselves with the local folder, downloaded into the read cache with S3). 404
    ``UploadExpired`` when they are not all there."""
    gone = NotFound(f"upload {upload.id}: its bytes are gone", code="UploadExpired")
    try:
        folder = storage.local_dir(upload.storage_key)
        joined = _Joined([folder / name for name in upload.parts])
    except FileNotFoundError as exc:
        raise gone from exc
    if joined.size != upload.length:
        joined.close()
        raise gone
    with io.BufferedReader(joined, buffer_size=CHUNK_BYTES) as fh:
        yield cast(BinaryIO, fh)


@contextmanager
def _heartbeat(factory: sessionmaker[Session], upload_id: str) -> Iterator[None]:
    """While the block runs, a thread writes the upload's ``heartbeat_at`` every
    :data:`FINISH_BEAT_S` (as long as it is ``processing``)."""
    stop = threading.Event()

    def beat() -> None:
        while not stop.wait(FINISH_BEAT_S):
            try:
                with factory.begin() as session:
                    session.execute(
                        update(ResumableUpload)
                        .where(
                            ResumableUpload.id == upload_id,
                            ResumableUpload.state == UploadState.processing,
                        )
                        .values(heartbeat_at=utcnow())
                    )
            except Exception:  # the next beat tries again
                log.exception("upload %s: could not write its heartbeat", upload_id)

    thread = threading.Thread(target=beat, name=f"upload-{upload_id}-heartbeat", daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()


def _claim(factory: sessionmaker[Session], upload_id: str) -> ResumableUpload:
    """Mark a complete upload ``processing`` for this request; an upload that already ended
    is returned as it is. 423 while another request ingests it (its heartbeat is fresh)."""
    with factory.begin() as session:
        upload = session.get(ResumableUpload, upload_id, with_for_update=True)
        if upload is None:
            raise NotFound(f"upload {upload_id} not found")
        if upload.state in (UploadState.completed, UploadState.failed):
            return upload
        now = utcnow()
        if _alive(upload, now):
            raise _being_ingested(upload_id)
        check_offset(upload, upload.length)
        upload.state, upload.heartbeat_at = UploadState.processing, now
        return upload


def finish(
    factory: sessionmaker[Session],
    lookup: sessionmaker[Session],
    storage: Storage,
    settings: Settings,
    upload_id: str,
) -> ResumableUpload:
    """Ingest a complete upload's archive as a snapshot (:func:`ingest.create_snapshot`,
    ``lookup`` for its reads) and record the snapshot and job on the upload, in one
    transaction; the parts go after commit. 423 while another request does it.

    A refused archive (a DomainError: the single upload's 4xx) is recorded on the upload,
    its parts removed, and re-raised; an unexpected error puts the upload back to
    ``receiving``, so a PATCH at its full offset runs this again."""
    upload = _claim(factory, upload_id)
    if upload.state != UploadState.processing:
        return upload
    try:
        with _heartbeat(factory, upload_id), _archive(storage, upload) as archive:
            _check_sha256(archive, upload)
            archive.seek(0)
            with factory.begin() as session:
                result = ingest.create_snapshot(
                    session,
                    storage,
                    settings,
                    upload.environment_id,
                    ingest.UploadFiles(archive=ingest.UploadPart(upload.filename, archive)),
                    idempotency_key=upload.idempotency_key,
                    lookup=lookup,
                )
                row = session.get(ResumableUpload, upload_id, with_for_update=True)
                if row is None:
                    raise NotFound(f"upload {upload_id} was deleted while it was ingested")
                if row.state != UploadState.processing:
                    raise _TakenOver  # this request stalled; another one finished it
                row.state, row.completed_at = UploadState.completed, utcnow()
                row.snapshot_id, row.job_id = result.snapshot.id, result.job.id
                retention.delete_after_commit(session, storage, row.storage_key)
        return row
    except _TakenOver:
        with factory.begin() as session:
            ended = session.get(ResumableUpload, upload_id)
        if ended is None:
            raise NotFound(f"upload {upload_id} not found") from None
        return ended
    except DomainError as exc:
        if exc.status_code >= 500:  # a full disk: not the archive's fault, keep its bytes
            _back_to_receiving(factory, upload_id)
            raise
        with factory.begin() as session:
            row = session.get(ResumableUpload, upload_id, with_for_update=True)
            if row is not None and row.state == UploadState.completed:
                return row  # this request stalled and another finished it (its parts gone)
            if row is not None:
                row.state, row.completed_at = UploadState.failed, utcnow()
                row.error_status, row.error_code = exc.status_code, exc.code
                row.error_detail = exc.detail
                retention.delete_after_commit(session, storage, row.storage_key)
        raise
    except BaseException:
        _back_to_receiving(factory, upload_id)
        raise


class _TakenOver(Exception):
    """The finishing request found its upload ended by another that took over after its
    heartbeat went stale: its own snapshot is rolled back."""


def _back_to_receiving(factory: sessionmaker[Session], upload_id: str) -> None:
    with factory.begin() as session:
        row = session.get(ResumableUpload, upload_id, with_for_update=True)
        if row is not None and row.state == UploadState.processing:
            row.state, row.heartbeat_at = UploadState.receiving, None


def _check_sha256(archive: BinaryIO, upload: ResumableUpload) -> None:
    """422 ``ArchiveChecksumMismatch`` when the archive's SHA-256 is not the declared one."""
    if upload.sha256 is None:
        return
    digest = hashlib.sha256()
    while chunk := archive.read(CHUNK_BYTES):
        digest.update(chunk)
    if digest.hexdigest() != upload.sha256:
        raise InvalidInput(
            f"{upload.filename}: the uploaded bytes' SHA-256 is {digest.hexdigest()}, not the "
            f"declared {upload.sha256}",
            code="ArchiveChecksumMismatch",
        )


def terminate(session: Session, storage: Storage, upload: ResumableUpload) -> None:
    """Delete the upload and its parts (after commit); 423 while its archive is being
    ingested. A snapshot it made stays."""
    row = session.get(ResumableUpload, upload.id, with_for_update=True)
    if row is None:
        raise NotFound(f"upload {upload.id} not found")
    if _alive(row, utcnow()):
        raise _being_ingested(upload.id)
    session.delete(row)
    session.flush()
    retention.delete_after_commit(session, storage, row.storage_key)


def expire(
    session: Session, storage: Storage, orphan_age_s: float, now: datetime | None = None
) -> dict[str, int]:
    """Delete uploads past ``expires_at`` (rows now, parts after commit; one being ingested
    waits for the next run), part folders with no row once ``orphan_age_s`` old, and parts
    that killed requests left half-written for that long (spooled in this host's scratch,
    or unfinished multipart uploads in S3). Returns counts by kind."""
    now = now or utcnow()
    counts = {"uploads_expired": 0, "uploads_orphaned": 0}
    expired = session.scalars(
        select(ResumableUpload).where(ResumableUpload.expires_at <= now)
    ).all()
    gone: list[str] = []
    for upload in expired:
        if _alive(upload, now):
            continue
        gone.append(upload.id)
        retention.delete_after_commit(session, storage, upload.storage_key)
    if gone:
        session.execute(delete(ResumableUpload).where(ResumableUpload.id.in_(gone)))
        counts["uploads_expired"] = len(gone)
    cutoff = now.timestamp() - orphan_age_s
    folders = storage.folders(FOLDER)
    names = list(folders)
    known = {
        upload_id
        for start in range(0, len(names), 500)
        for upload_id in session.scalars(
            select(ResumableUpload.id).where(ResumableUpload.id.in_(names[start : start + 500]))
        )
    }
    for name, newest in folders.items():
        if name not in known and name not in gone and newest < cutoff:
            storage.delete_prefix(f"{FOLDER}/{name}")
            counts["uploads_orphaned"] += 1
    counts["uploads_orphaned"] += storage.remove_partial(FOLDER, cutoff)
    return counts


def sweep_spools(storage: Storage, older_than: float) -> int:
    """Remove the PATCH spool files (``uploads/<id>/.<part>.part``) in this host's scratch
    last written before ``older_than`` (s since the epoch): those of requests killed with
    their process. Each API host runs it at start, as no other host sees its scratch.
    Returns how many."""
    return remove_older(storage.scratch_path(FOLDER), "*/.*.part", older_than)


def expires_header(when: datetime) -> str:
    """An RFC 9110 HTTP date (``Upload-Expires``)."""
    return time.strftime("%a, %d %b %Y %H:%M:%S GMT", time.gmtime(when.timestamp()))
