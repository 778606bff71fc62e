"""Blob storage addressed by relative keys (``snapshots/<id>/images/a.jpg``): one interface,
:class:`Storage`, and its backends, chosen by :func:`open_storage` from the settings.

- :class:`LocalStorage`: files below one folder (the embedded default). Its scratch is the
  same folder, so staging and job work folders live where they always did.
- :class:`S3Storage`: objects in an S3-compatible bucket (boto3; docs/decisions/storage.md),
  so API and worker hosts share nothing but the database, the broker and the bucket. Each
  host keeps a private scratch folder: ``<scratch>/local`` for files written in place and
  ``<scratch>/cache`` for read copies (downloaded once, trimmed least recently used first).

Writes stream in chunks and land atomically (temporary file, then rename), so a reader
never sees half a file and a failed upload leaves nothing under its key.

Code that needs a file on disk asks for :meth:`Storage.local_file` / :meth:`Storage.local_dir`
(read-only copies) or :meth:`Storage.scratch_path` (a writable path on this host only: a
tus PATCH's body as it arrives, upload staging, job work folders), never for a path inside
the store.
"""

from __future__ import annotations

import errno
import hashlib
import os
import shutil
import threading
import time
import uuid
from abc import ABC, abstractmethod
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime
from functools import lru_cache
from io import BytesIO, RawIOBase
from pathlib import Path, PurePosixPath
from typing import Any, BinaryIO, cast

from app.core.errors import InvalidInput
from app.core.settings import Settings, parse_s3_url

CHUNK_BYTES = 1024 * 1024


@dataclass(frozen=True)
class StoredBlob:
    key: str
    size_bytes: int
    sha256: str


def check_key(key: str) -> PurePosixPath:
    """``key`` as a relative POSIX path; InvalidInput for an empty, absolute or ``..`` key."""
    pure = PurePosixPath(key)
    if pure.is_absolute() or ".." in pure.parts or not pure.parts:
        raise InvalidInput(f"invalid storage key {key!r}")
    return pure


def _below(root: Path, key: str) -> Path:
    return root.joinpath(*check_key(key).parts)


class _HashingReader(RawIOBase):
    """``source`` read through: counts and hashes the bytes, OverflowError past ``max_bytes``."""

    def __init__(self, source: BinaryIO, key: str, max_bytes: int | None) -> None:
        self.source, self.key, self.max_bytes = source, key, max_bytes
        self.size = 0
        self.digest = hashlib.sha256()

    def readable(self) -> bool:
        return True

    def read(self, size: int | None = -1) -> bytes:
        chunk = self.source.read(-1 if size is None else size)
        self.size += len(chunk)
        if self.max_bytes is not None and self.size > self.max_bytes:
            raise OverflowError(f"{self.key}: more than {self.max_bytes} bytes")
        self.digest.update(chunk)
        return chunk


class Storage(ABC):
    """Where blobs live, plus ``scratch``: this host's private folder for files that are
    written in place (never shared between hosts). Every method raises InvalidInput for a
    bad key (:func:`check_key`); reads of a missing key raise FileNotFoundError."""

    scratch: Path

    @abstractmethod
    def local_file(self, key: str) -> Path:
        """A readable local file with the object's bytes (do not write to it)."""

    @abstractmethod
    def local_dir(self, prefix: str) -> Path:
        """Every object under ``prefix/`` as files in a local folder (do not write to it);
        FileNotFoundError when nothing is stored under it."""

    @abstractmethod
    def cached_file(self, key: str) -> Path | None:
        """A local file of ``key`` when this host has one without copying; None when the
        object must be streamed (:meth:`iter_bytes`) or is missing."""

    @abstractmethod
    def write_stream(self, key: str, source: BinaryIO, max_bytes: int | None = None) -> StoredBlob:
        """Copy ``source`` to ``key`` in chunks (never whole in memory); raises
        ``OverflowError`` past ``max_bytes``, leaving nothing under ``key``."""

    @abstractmethod
    def move_in(self, local: Path, key: str) -> None:
        """A staged file or folder (under :attr:`scratch`) becomes ``key``; the local copy
        is gone afterwards."""

    @abstractmethod
    def exists(self, key: str) -> bool:
        """Whether ``key`` is an object or a folder holding some."""

    @abstractmethod
    def open(self, key: str) -> BinaryIO:
        """A streaming reader of the object's bytes."""

    @abstractmethod
    def modified_ns(self, key: str) -> int | None:
        """When the object was last written (ns since the epoch), None when missing."""

    @abstractmethod
    def delete_prefix(self, key: str) -> None:
        """Remove a file or a whole folder (and this host's copies of it); missing is fine."""

    @abstractmethod
    def folders(self, prefix: str) -> dict[str, float]:
        """The folders directly under ``prefix/`` by name, each with the newest modification
        time (s since the epoch) of anything in it; empty when there are none."""

    @abstractmethod
    def remove_partial(self, prefix: str, older_than: float) -> int:
        """Drop unfinished writes under ``prefix/`` (left by killed processes) started
        before ``older_than`` (s since the epoch); returns how many."""

    @abstractmethod
    def check(self) -> None:
        """Raise OSError (``strerror`` says what is wrong) unless the store is writable."""

    def scratch_path(self, key: str) -> Path:
        """A writable path for ``key`` on this host, under :attr:`scratch` (the parent
        folder is not created)."""
        return _below(self.scratch, key)

    def tmp_dir(self) -> Path:
        """A fresh private folder under :attr:`scratch` for staging; caller removes it."""
        path = self.scratch_path(".tmp") / uuid.uuid4().hex
        path.mkdir(parents=True)
        return path

    def write_bytes(self, key: str, data: bytes) -> StoredBlob:
        return self.write_stream(key, BytesIO(data))

    def iter_bytes(self, key: str) -> Iterator[bytes]:
        """The object's bytes in chunks of :data:`CHUNK_BYTES`."""
        with self.open(key) as fh:
            while chunk := fh.read(CHUNK_BYTES):
                yield chunk


class LocalStorage(Storage):
    """Blobs as files below ``root``; ``scratch`` is ``root`` itself."""

    def __init__(self, root: Path) -> None:
        self.root = root.resolve()
        self.root.mkdir(parents=True, exist_ok=True)
        self.scratch = self.root

    def path(self, key: str) -> Path:
        """The file of ``key`` below the root, present or not (this backend only; service
        code uses :meth:`local_file` or :meth:`scratch_path`)."""
        return _below(self.root, key)

    def local_file(self, key: str) -> Path:
        path = self.path(key)
        if not path.is_file():
            raise FileNotFoundError(f"no stored file {key!r}")
        return path

    def local_dir(self, prefix: str) -> Path:
        path = self.path(prefix)
        if not path.is_dir():
            raise FileNotFoundError(f"no stored folder {prefix!r}")
        return path

    def cached_file(self, key: str) -> Path | None:
        path = self.path(key)
        return path if path.is_file() else None

    def write_stream(self, key: str, source: BinaryIO, max_bytes: int | None = None) -> StoredBlob:
        target = self.path(key)
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = target.with_name(f".{target.name}.{uuid.uuid4().hex}.part")
        reader = _HashingReader(source, key, max_bytes)
        try:
            with tmp.open("wb") as out:
                while chunk := reader.read(CHUNK_BYTES):
                    out.write(chunk)
            os.replace(tmp, target)
        finally:
            tmp.unlink(missing_ok=True)
        return StoredBlob(key=key, size_bytes=reader.size, sha256=reader.digest.hexdigest())

    def move_in(self, local: Path, key: str) -> None:
        """Same file system: a rename (an existing file under ``key`` is replaced)."""
        target = self.path(key)
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.move(str(local), str(target))

    def exists(self, key: str) -> bool:
        return self.path(key).exists()

    def open(self, key: str) -> BinaryIO:
        return self.path(key).open("rb")

    def modified_ns(self, key: str) -> int | None:
        try:
            return self.path(key).stat().st_mtime_ns
        except FileNotFoundError:
            return None

    def delete_prefix(self, key: str) -> None:
        _remove(self.path(key))

    def folders(self, prefix: str) -> dict[str, float]:
        try:
            entries = [e for e in os.scandir(self.path(prefix)) if e.is_dir()]
        except FileNotFoundError:
            return {}
        newest: dict[str, float] = {}
        for entry in entries:
            try:
                newest[entry.name] = _newest_mtime(Path(entry.path))
            except FileNotFoundError:
                continue  # removed meanwhile
        return newest

    def remove_partial(self, prefix: str, older_than: float) -> int:
        """write_stream's ``.<name>.<hex>.part`` files."""
        return remove_older(self.path(prefix), "*/**/.*.part", older_than)

    def check(self) -> None:
        self.tmp_dir().rmdir()


def remove_older(folder: Path, pattern: str, older_than: float) -> int:
    """Delete the files below ``folder`` matching the glob ``pattern`` last written before
    ``older_than`` (s since the epoch); returns how many. A missing folder or a file gone
    meanwhile is skipped."""
    removed = 0
    for path in folder.glob(pattern) if folder.is_dir() else ():
        try:
            if path.stat().st_mtime < older_than:
                path.unlink(missing_ok=True)
                removed += 1
        except FileNotFoundError:
            continue
    return removed


def _remove(path: Path) -> None:
    """Remove a local file or folder tree; missing is fine."""
    if path.is_dir():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


def _newest_mtime(folder: Path) -> float:
    """The newest modification time of ``folder`` and everything in it."""
    newest = folder.stat().st_mtime
    for root, dirs, files in os.walk(folder):
        for name in (*dirs, *files):
            try:
                newest = max(newest, os.stat(os.path.join(root, name)).st_mtime)
            except FileNotFoundError:
                continue
    return newest


# --- S3 -----------------------------------------------------------------------------------------

PART_BYTES = 8 * 1024 * 1024  # multipart part size: S3's minimum is 5 MiB, 10 000 parts at most
STREAM_PARTS = 1  # parts of a streamed write in memory at once (see S3Storage)
TRANSFER_THREADS = 4  # parts in flight per transfer
DOWNLOAD_THREADS = 8  # files fetched at once by local_dir, sent at once by move_in
DELETE_BATCH = 1000  # S3's DeleteObjects limit
TRIM_INTERVAL_S = 60.0  # a process walks the cache to trim it at most this often
# Cache files handed out within this long are never trimmed (a running job reads them);
# raise scratch_cache_max_bytes rather than this when jobs need more.
TRIM_KEEP_RECENT_S = 3600.0
_MISSING = {"404", "NoSuchKey", "NotFound"}  # error codes of a missing key


@dataclass(frozen=True)
class _ObjectStat:
    size_bytes: int
    modified_ns: int  # LastModified, whole seconds (HEAD and LIST agree on those)


def _modified_ns(when: datetime) -> int:
    return int(when.timestamp()) * 1_000_000_000


class S3Storage(Storage):
    """Objects ``<prefix>/<key>`` in ``bucket``; ``scratch_root`` is this host's private folder
    (``local/`` for :meth:`scratch_path`, ``cache/`` for read copies). ``client`` is a boto3 S3
    client. Bucket errors other than a missing key raise OSError (errno EIO) saying what
    failed; a missing key raises FileNotFoundError."""

    def __init__(
        self, bucket: str, prefix: str, scratch_root: Path, client: Any, cache_max_bytes: int
    ) -> None:
        from boto3.s3.transfer import TransferConfig

        self.bucket, self.prefix, self.client = bucket, prefix.strip("/"), client
        root = scratch_root.resolve()
        self.scratch, self.cache = root / "local", root / "cache"
        self.scratch.mkdir(parents=True, exist_ok=True)
        self.cache.mkdir(parents=True, exist_ok=True)
        self.cache_max_bytes = cache_max_bytes
        self.transfer = TransferConfig(
            multipart_threshold=PART_BYTES,
            multipart_chunksize=PART_BYTES,
            max_concurrency=TRANSFER_THREADS,
        )
        # write_stream's source cannot seek, so s3transfer keeps each part it read in memory
        # until it is sent: STREAM_PARTS of them at most (s3transfer's default is 10)
        self.stream_transfer = TransferConfig(
            multipart_threshold=PART_BYTES,
            multipart_chunksize=PART_BYTES,
            max_concurrency=STREAM_PARTS,
        )
        self.stream_transfer.max_in_memory_upload_chunks = STREAM_PARTS
        self._trimmed_at = 0.0
        self._trim_lock = threading.Lock()

    # keys and errors

    def _object(self, key: str) -> str:
        """The bucket key of storage key ``key``."""
        pure = check_key(key).as_posix()
        return f"{self.prefix}/{pure}" if self.prefix else pure

    def _cache_path(self, key: str) -> Path:
        return _below(self.cache, key)

    @contextmanager
    def _errors(self, what: str) -> Iterator[None]:
        from botocore.exceptions import BotoCoreError, ClientError

        try:
            yield
        except ClientError as exc:
            error = exc.response.get("Error", {})
            code = str(error.get("Code", ""))
            if code in _MISSING:
                raise FileNotFoundError(errno.ENOENT, f"no stored object {what!r}") from exc
            detail = f"bucket {self.bucket}: {what}: {code} {error.get('Message', '')}".strip()
            raise OSError(errno.EIO, detail) from exc
        except BotoCoreError as exc:
            raise OSError(errno.EIO, f"bucket {self.bucket}: {what}: {exc}") from exc

    def _stat(self, key: str) -> _ObjectStat | None:
        try:
            with self._errors(key):
                head = self.client.head_object(Bucket=self.bucket, Key=self._object(key))
        except FileNotFoundError:
            return None
        return _ObjectStat(int(head["ContentLength"]), _modified_ns(head["LastModified"]))

    def _list(self, prefix: str) -> Iterator[tuple[str, _ObjectStat]]:
        """(path below ``prefix/``, stat) of every object under it."""
        start = self._object(prefix) + "/"
        with self._errors(f"{prefix}/"):
            pages = self.client.get_paginator("list_objects_v2").paginate(
                Bucket=self.bucket, Prefix=start
            )
            for page in pages:
                for item in page.get("Contents", ()):
                    stat = _ObjectStat(int(item["Size"]), _modified_ns(item["LastModified"]))
                    yield item["Key"][len(start) :], stat

    # the read cache

    def _fresh(self, path: Path, stat: _ObjectStat) -> bool:
        """Whether the cache file ``path`` holds the object ``stat`` describes (its size and
        LastModified, kept as the file's mtime); marks it used when so."""
        try:
            own = path.stat()
        except FileNotFoundError:
            return False
        if own.st_size != stat.size_bytes or own.st_mtime_ns != stat.modified_ns:
            return False
        try:
            os.utime(path, ns=(time.time_ns(), stat.modified_ns))
        except FileNotFoundError:  # trimmed meanwhile
            return False
        return True

    def _download(self, key: str, stat: _ObjectStat) -> Path:
        """Fetch ``key`` into the cache: a part file renamed into place, so processes on
        this host that fetch it at once each leave a whole file."""
        path = self._cache_path(key)
        if self._fresh(path, stat):
            return path
        path.parent.mkdir(parents=True, exist_ok=True)
        part = path.with_name(f".{path.name}.{uuid.uuid4().hex}.part")
        try:
            with self._errors(key), part.open("wb") as out:
                self.client.download_fileobj(
                    self.bucket, self._object(key), out, Config=self.transfer
                )
            os.utime(part, ns=(time.time_ns(), stat.modified_ns))
            os.replace(part, path)
        finally:
            part.unlink(missing_ok=True)
        return path

    def _upload(self, local: Path, key: str) -> None:
        """Upload the file ``local`` as ``key`` (multipart past ``PART_BYTES``), then make it
        the cache copy of ``key``."""
        with self._errors(key):
            self.client.upload_file(
                str(local), self.bucket, self._object(key), Config=self.transfer
            )
        stat = self._stat(key)
        if stat is None:
            return
        path = self._cache_path(key)
        path.parent.mkdir(parents=True, exist_ok=True)
        os.utime(local, ns=(time.time_ns(), stat.modified_ns))
        shutil.move(str(local), str(path))

    def trim_cache(self, keep_recent_s: float = TRIM_KEEP_RECENT_S) -> int:
        """Remove cache files, least recently used first, until the cache holds at most
        ``cache_max_bytes`` (files used in the last ``keep_recent_s`` stay), and part files
        of downloads killed over an hour ago; returns the bytes removed."""
        now = time.time()
        files: list[tuple[float, int, Path]] = []
        for root, _dirs, names in os.walk(self.cache):
            for name in names:
                path = Path(root, name)
                try:
                    st = path.stat()
                except FileNotFoundError:
                    continue
                if name.endswith(".part"):
                    if st.st_mtime < now - 3600:
                        path.unlink(missing_ok=True)
                    continue
                files.append((st.st_atime, st.st_size, path))
        excess = sum(size for _, size, _ in files) - self.cache_max_bytes
        removed = 0
        for used, size, path in sorted(files):
            if removed >= excess or used > now - keep_recent_s:
                break
            path.unlink(missing_ok=True)
            removed += size
        return removed

    def _maybe_trim(self) -> None:
        with self._trim_lock:
            if time.monotonic() - self._trimmed_at < TRIM_INTERVAL_S:
                return
            self._trimmed_at = time.monotonic()
        self.trim_cache()

    # the interface

    def local_file(self, key: str) -> Path:
        stat = self._stat(key)
        if stat is None:
            raise FileNotFoundError(errno.ENOENT, f"no stored object {key!r}")
        path = self._download(key, stat)
        self._maybe_trim()
        return path

    def local_dir(self, prefix: str) -> Path:
        listed = dict(self._list(prefix))
        if not listed:
            raise FileNotFoundError(errno.ENOENT, f"no stored objects under {prefix!r}/")
        folder = self._cache_path(prefix)
        with ThreadPoolExecutor(DOWNLOAD_THREADS) as pool:
            list(
                pool.map(
                    lambda item: self._download(f"{prefix}/{item[0]}", item[1]), listed.items()
                )
            )
        for root, _dirs, names in os.walk(folder):  # files whose objects are gone
            for name in names:
                rel = Path(root, name).relative_to(folder).as_posix()
                if rel not in listed and not name.endswith(".part"):
                    Path(root, name).unlink(missing_ok=True)
        self._maybe_trim()
        return folder

    def cached_file(self, key: str) -> Path | None:
        stat = self._stat(key)
        path = self._cache_path(key)
        return path if stat is not None and self._fresh(path, stat) else None

    def write_stream(self, key: str, source: BinaryIO, max_bytes: int | None = None) -> StoredBlob:
        """A multipart upload of ``PART_BYTES`` parts (aborted on failure, so nothing is
        left under ``key``)."""
        reader = _HashingReader(source, key, max_bytes)
        with self._errors(key):
            self.client.upload_fileobj(
                reader, self.bucket, self._object(key), Config=self.stream_transfer
            )
        return StoredBlob(key=key, size_bytes=reader.size, sha256=reader.digest.hexdigest())

    def move_in(self, local: Path, key: str) -> None:
        """Each file is uploaded, then kept as this host's cache copy."""
        check_key(key)
        if local.is_dir():
            files = sorted(p for p in local.rglob("*") if p.is_file())
            pairs = [(p, f"{key}/{p.relative_to(local).as_posix()}") for p in files]
        elif local.is_file():
            pairs = [(local, key)]
        else:
            raise FileNotFoundError(errno.ENOENT, f"nothing to move in at {local}")
        with ThreadPoolExecutor(DOWNLOAD_THREADS) as pool:
            list(pool.map(lambda pair: self._upload(*pair), pairs))
        if local.is_dir():
            shutil.rmtree(local, ignore_errors=True)

    def exists(self, key: str) -> bool:
        if self._stat(key) is not None:
            return True
        with self._errors(key):
            page = self.client.list_objects_v2(
                Bucket=self.bucket, Prefix=self._object(key) + "/", MaxKeys=1
            )
        return bool(page.get("KeyCount", 0))

    def open(self, key: str) -> BinaryIO:
        """The object's StreamingBody (read in chunks, never whole)."""
        with self._errors(key):
            body = self.client.get_object(Bucket=self.bucket, Key=self._object(key))["Body"]
        return cast(BinaryIO, body)

    def modified_ns(self, key: str) -> int | None:
        stat = self._stat(key)
        return None if stat is None else stat.modified_ns

    def delete_prefix(self, key: str) -> None:
        """The object ``key`` and every object under ``key/`` (listed, then deleted in
        batches), then this host's cache and scratch copies."""
        doomed = [self._object(key)]
        doomed += [self._object(f"{key}/{rel}") for rel, _ in self._list(key)]
        for start in range(0, len(doomed), DELETE_BATCH):
            batch = [{"Key": name} for name in doomed[start : start + DELETE_BATCH]]
            with self._errors(key):
                answer = self.client.delete_objects(
                    Bucket=self.bucket, Delete={"Objects": batch, "Quiet": True}
                )
            if answer.get("Errors"):
                first = answer["Errors"][0]
                detail = f"{first.get('Code')} {first.get('Message', '')}"
                raise OSError(
                    errno.EIO, f"bucket {self.bucket}: delete {first.get('Key')}: {detail}"
                )
        _remove(self._cache_path(key))
        _remove(self.scratch_path(key))

    def folders(self, prefix: str) -> dict[str, float]:
        newest: dict[str, float] = {}
        for rel, stat in self._list(prefix):
            name, sep, _ = rel.partition("/")
            if sep:
                newest[name] = max(newest.get(name, 0.0), stat.modified_ns / 1e9)
        return newest

    def remove_partial(self, prefix: str, older_than: float) -> int:
        """Multipart uploads under ``prefix/`` begun before ``older_than`` and never
        completed (a killed process); aborted, which frees their parts."""
        aborted = 0
        with self._errors(f"{prefix}/"):
            pages = self.client.get_paginator("list_multipart_uploads").paginate(
                Bucket=self.bucket, Prefix=self._object(prefix) + "/"
            )
            for page in pages:
                for upload in page.get("Uploads", ()):
                    if upload["Initiated"].timestamp() < older_than:
                        self.client.abort_multipart_upload(
                            Bucket=self.bucket, Key=upload["Key"], UploadId=upload["UploadId"]
                        )
                        aborted += 1
        return aborted

    def check(self) -> None:
        """HEAD the bucket, then make and remove a folder in scratch."""
        try:
            with self._errors("HEAD bucket"):
                self.client.head_bucket(Bucket=self.bucket)
        except FileNotFoundError as exc:  # HEAD answers a bare 404
            raise OSError(errno.ENOENT, f"bucket {self.bucket}: no such bucket") from exc
        self.tmp_dir().rmdir()


def open_storage(settings: Settings) -> Storage:
    """The storage the settings name: an S3 bucket for ``storage_url``, else the local
    folder ``resolved_storage_dir``. One S3 client per process and location (boto3 clients
    are thread-safe; a forked worker makes its own)."""
    if settings.storage_url is None:
        return LocalStorage(settings.resolved_storage_dir)
    bucket, prefix = parse_s3_url(settings.storage_url)
    with _OPENING:
        return _s3_storage(
            os.getpid(),
            bucket,
            prefix,
            settings.s3_endpoint_url,
            settings.s3_region,
            settings.resolved_scratch_dir,
            settings.scratch_cache_max_bytes,
        )


_OPENING = threading.Lock()  # one client per location even when threads open it at once


@lru_cache(maxsize=8)
def _s3_storage(
    _pid: int,
    bucket: str,
    prefix: str,
    endpoint_url: str | None,
    region: str | None,
    scratch: Path,
    cache_max_bytes: int,
) -> S3Storage:
    import boto3
    from botocore.config import Config

    client = boto3.session.Session().client(
        "s3",
        endpoint_url=endpoint_url,
        region_name=region,
        config=Config(
            retries={"mode": "standard", "max_attempts": 3},
            connect_timeout=5,
            read_timeout=60,
            max_pool_connections=DOWNLOAD_THREADS * TRANSFER_THREADS,
        ),
    )
    return S3Storage(bucket, prefix, scratch, client, cache_max_bytes)
