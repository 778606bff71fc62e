"""Resumable uploads (tus 1.0: core, creation, termination, checksum, expiration) of one
capture archive (.zip, .tar, .tar.gz), for capture stations on connections that drop.

An upload is a row (:class:`~app.core.models.ResumableUpload`) and a partial file
``uploads/<id>`` in the receiving API host's scratch (:meth:`Storage.scratch_path`; with S3
storage several API hosts need sticky routing for /v1/uploads). **The file's size is the
upload's offset**: a PATCH appends to it under an exclusive ``flock`` (one writer at a
time, in any API process on the host), and bytes that arrived before a connection dropped
stay (unless the chunk carried a checksum, which they could not match). When the last byte
is in, the archive goes through the same ingest as a single-request archive upload
(:func:`app.core.ingest.create_snapshot`: the same checks, errors and ``Idempotency-Key``
semantics); the snapshot and its job are recorded on the upload in the same transaction,
and the file goes once that commits. A refused archive keeps its error on the row and loses
its bytes.

Every write moves ``expires_at`` to ``upload_expiry_s`` from now; :func:`expire` (beat's
``maintenance.uploads``) deletes expired uploads, their files, and partial files without a
row.
"""

from __future__ import annotations

import base64
import binascii
import fcntl
import hashlib
import os
import re
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any, BinaryIO

from sqlalchemy import delete, select
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
from app.core.storage import Storage

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
_SHA256 = re.compile(r"^[0-9a-f]{64}$")


class BadRequest(DomainError):
    """400: a tus header is missing or malformed."""

    status_code = 400
    code = "BadRequest"


class UploadLocked(DomainError):
    """423: another request is writing this upload (a PATCH whose connection dropped is
    still saving); retry after a short wait."""

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


def create(
    session: Session, storage: Storage, settings: Settings, new: NewUpload
) -> tuple[ResumableUpload, bool]:
    """A new upload with an empty partial file, or the unexpired upload that already has
    this ``idempotency_key``, ``sha256`` and length (so a client that lost its upload URL
    resumes instead of sending everything again); returns (upload, created).

    404 for an unknown environment; 413 beyond ``max_upload_bytes``; 415 for a name that is
    not an archive; 507 when the partial file cannot be made."""
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
        if earlier is not None and (
            earlier.state != UploadState.receiving
            or storage.scratch_path(earlier.storage_key).exists()
        ):
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
        expires_at=utcnow() + timedelta(seconds=settings.upload_expiry_s),
    )
    path = storage.scratch_path(upload.storage_key)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.touch(exist_ok=False)
    except OSError as exc:
        if _disk_full(exc):
            raise _no_space("upload") from exc
        raise
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


def offset(storage: Storage, upload: ResumableUpload) -> int:
    """Bytes received: the partial file's size while receiving, the length afterwards;
    404 when a receiving upload's file is gone."""
    if upload.state != UploadState.receiving:
        return upload.length
    try:
        return storage.scratch_path(upload.storage_key).stat().st_size
    except FileNotFoundError:
        raise NotFound(f"upload {upload.id}: its bytes are gone", code="UploadExpired") from None


def touch(session: Session, upload_id: str, settings: Settings) -> datetime:
    """Move the upload's expiry to ``upload_expiry_s`` from now; returns it."""
    expires_at = utcnow() + timedelta(seconds=settings.upload_expiry_s)
    upload = session.get(ResumableUpload, upload_id, with_for_update=True)
    if upload is not None:
        upload.expires_at = expires_at
    return expires_at


# --- writing --------------------------------------------------------------------------------


def _lock(path: Path, upload_id: str) -> int:
    """An open descriptor of ``path`` holding its exclusive lock; 404 when the file is gone,
    423 ``UploadLocked`` while another request holds it."""
    try:
        fd = os.open(path, os.O_RDWR)
    except FileNotFoundError:
        raise NotFound(f"upload {upload_id}: its bytes are gone", code="UploadExpired") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise UploadLocked(
            f"upload {upload_id}: another request is writing it; retry in a moment"
        ) from None
    return fd


class Receiver:
    """One PATCH's bytes appended to an upload's partial file, holding its lock from
    :meth:`open` to :meth:`close`.

    ``start`` is the request's Upload-Offset (409 ``OffsetMismatch`` unless it is the file's
    size), ``limit`` the most bytes the chunk may carry (413 past it), ``checksum`` the
    chunk's Upload-Checksum (460 and the chunk discarded when it does not match)."""

    def __init__(
        self, path: Path, upload_id: str, start: int, limit: int, checksum: tuple[str, bytes] | None
    ) -> None:
        self.path, self.upload_id, self.start, self.limit = path, upload_id, start, limit
        self.checksum = checksum
        self.hasher = CHECKSUMS[checksum[0]]() if checksum else None
        self.written = 0
        self._fh: BinaryIO | None = None

    def open(self) -> None:
        fd = _lock(self.path, self.upload_id)
        size = os.fstat(fd).st_size
        if size != self.start:
            os.close(fd)
            raise Conflict(
                f"Upload-Offset {self.start} is not the upload's offset {size}: HEAD it and "
                "resume from there",
                code="OffsetMismatch",
            )
        self._fh = os.fdopen(fd, "r+b")
        self._fh.seek(self.start)

    @property
    def fh(self) -> BinaryIO:
        if self._fh is None:
            raise RuntimeError("Receiver.open() first")
        return self._fh

    def write(self, data: bytes | bytearray) -> None:
        """Append ``data``; 413 past ``limit``, 507 on a full disk (either discards the chunk)."""
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
        returns the new offset."""
        self.fh.flush()
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
        return self.start + self.written

    def keep_partial(self) -> int:
        """After a dropped connection: keep the bytes that arrived, unless the chunk has a
        checksum (they cannot be verified); returns the offset."""
        if self.checksum is not None:
            self.rollback()
            return self.start
        self.fh.flush()
        return self.start + self.written

    def rollback(self) -> None:
        """Discard this chunk: the file back to ``start`` bytes."""
        self.fh.flush()
        self.fh.truncate(self.start)
        self.written = 0

    def close(self) -> None:
        """Release the lock."""
        if self._fh is not None:
            self._fh.close()
            self._fh = None


# --- the end of an upload -------------------------------------------------------------------


def finish(
    factory: sessionmaker[Session],
    lookup: sessionmaker[Session],
    storage: Storage,
    settings: Settings,
    upload_id: str,
) -> ResumableUpload:
    """Ingest a complete upload's archive as a snapshot (:func:`ingest.create_snapshot`,
    ``lookup`` for its reads) and record the snapshot and job on the upload, in one
    transaction; the file goes after commit. The caller holds the file's lock.

    A refused archive (a DomainError: the single upload's 4xx) is recorded on the upload,
    its file removed, and re-raised; an unexpected error puts the upload back to
    ``receiving``, so a PATCH at its full offset runs this again."""
    with factory.begin() as session:
        upload = session.get(ResumableUpload, upload_id, with_for_update=True)
        if upload is None:
            raise NotFound(f"upload {upload_id} not found")
        if upload.state in (UploadState.completed, UploadState.failed):
            return upload
        upload.state = UploadState.processing
    try:
        archive = storage.scratch_path(upload.storage_key)
        _check_sha256(archive, upload)
        with factory.begin() as session, archive.open("rb") as fh:
            result = ingest.create_snapshot(
                session,
                storage,
                settings,
                upload.environment_id,
                ingest.UploadFiles(archive=ingest.UploadPart(upload.filename, fh)),
                idempotency_key=upload.idempotency_key,
                lookup=lookup,
            )
            row = session.get(ResumableUpload, upload_id, with_for_update=True)
            if row is None:
                raise NotFound(f"upload {upload_id} was deleted while it was ingested")
            row.state, row.completed_at = UploadState.completed, utcnow()
            row.snapshot_id, row.job_id = result.snapshot.id, result.job.id
            retention.delete_after_commit(session, storage, row.storage_key)
        return row
    except DomainError as exc:
        if exc.status_code >= 500:  # a full disk: not the archive's fault, keep its bytes
            _back_to_receiving(factory, upload_id)
            raise
        with factory.begin() as session:
            row = session.get(ResumableUpload, upload_id, with_for_update=True)
            if row is not None:
                row.state, row.completed_at = UploadState.failed, utcnow()
                row.error_status, row.error_code = exc.status_code, exc.code
                row.error_detail = exc.detail
                retention.delete_after_commit(session, storage, row.storage_key)
        raise
    except BaseException:
        _back_to_receiving(factory, upload_id)
        raise


def _back_to_receiving(factory: sessionmaker[Session], upload_id: str) -> None:
    with factory.begin() as session:
        row = session.get(ResumableUpload, upload_id, with_for_update=True)
        if row is not None and row.state == UploadState.processing:
            row.state = UploadState.receiving


def _check_sha256(path: Path, upload: ResumableUpload) -> None:
    """422 ``ArchiveChecksumMismatch`` when the archive's SHA-256 is not the declared one."""
    if upload.sha256 is None:
        return
    digest = hashlib.sha256()
    with path.open("rb") as fh:
        while chunk := fh.read(4 * 1024 * 1024):
            digest.update(chunk)
    if digest.hexdigest() != upload.sha256:
        raise InvalidInput(
            f"{upload.filename}: the uploaded bytes' SHA-256 is {digest.hexdigest()}, not the "
            f"declared {upload.sha256}",
            code="ArchiveChecksumMismatch",
        )


def terminate(session: Session, storage: Storage, upload: ResumableUpload) -> None:
    """Delete the upload and its bytes (after commit); 423 while a request writes it or its
    archive is being ingested. A snapshot it made stays."""
    path = storage.scratch_path(upload.storage_key)
    if path.exists():
        os.close(_lock(path, upload.id))  # only to learn that nobody holds it
    session.delete(upload)
    session.flush()
    retention.delete_after_commit(session, storage, upload.storage_key)


def _locked(path: Path) -> bool:
    try:
        os.close(_lock(path, ""))
    except UploadLocked:
        return True
    except NotFound:
        return False
    return False


def expire(
    session: Session, storage: Storage, orphan_age_s: float, now: datetime | None = None
) -> dict[str, int]:
    """Delete uploads past ``expires_at`` (rows now, files after commit; one a request is
    writing waits for the next run) and partial files with no row once ``orphan_age_s``
    old. Returns counts by kind."""
    now = now or utcnow()
    counts = {"uploads_expired": 0, "uploads_orphaned": 0}
    expired = session.scalars(
        select(ResumableUpload).where(ResumableUpload.expires_at <= now)
    ).all()
    gone: list[str] = []
    for upload in expired:
        if _locked(storage.scratch_path(upload.storage_key)):
            continue
        gone.append(upload.id)
        retention.delete_after_commit(session, storage, upload.storage_key)
    if gone:
        session.execute(delete(ResumableUpload).where(ResumableUpload.id.in_(gone)))
        counts["uploads_expired"] = len(gone)
    folder = storage.scratch_path(FOLDER)
    names = [p.name for p in folder.iterdir() if p.is_file()] if folder.is_dir() else []
    known = {
        upload_id
        for start in range(0, len(names), 500)
        for upload_id in session.scalars(
            select(ResumableUpload.id).where(ResumableUpload.id.in_(names[start : start + 500]))
        )
    }
    cutoff = now.timestamp() - orphan_age_s
    for name in names:
        path = folder / name
        try:
            old = path.stat().st_mtime < cutoff
        except FileNotFoundError:
            continue
        if name not in known and old and not _locked(path):
            path.unlink(missing_ok=True)
            counts["uploads_orphaned"] += 1
    return counts


def expires_header(when: datetime) -> str:
    """An RFC 9110 HTTP date (``Upload-Expires``)."""
    return time.strftime("%a, %d %b %Y %H:%M:%S GMT", time.gmtime(when.timestamp()))
