"""Blob storage addressed by relative keys (``snapshots/<id>/images/a.jpg``): one interface,
:class:`Storage`, and its backends, chosen by :func:`open_storage` from the settings.

- :class:`LocalStorage`: files below one folder (the embedded default). Its scratch is the
  same folder, so staging, job work folders and partial uploads live where they always did.

Writes stream in chunks and land atomically (temporary file, then rename), so a reader
never sees half a file and a failed upload leaves nothing under its key.

Code that needs a file on disk asks for :meth:`Storage.local_file` / :meth:`Storage.local_dir`
(read-only copies) or :meth:`Storage.scratch_path` (a writable path on this host only: tus
partial files, upload staging, job work folders), never for a path inside the store.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import uuid
from abc import ABC, abstractmethod
from collections.abc import Iterator
from dataclasses import dataclass
from io import BytesIO
from pathlib import Path, PurePosixPath
from typing import BinaryIO

from app.core.errors import InvalidInput
from app.core.settings import Settings

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
        digest = hashlib.sha256()
        size = 0
        try:
            with tmp.open("wb") as out:
                while chunk := source.read(CHUNK_BYTES):
                    size += len(chunk)
                    if max_bytes is not None and size > max_bytes:
                        raise OverflowError(f"{key}: more than {max_bytes} bytes")
                    digest.update(chunk)
                    out.write(chunk)
            os.replace(tmp, target)
        finally:
            tmp.unlink(missing_ok=True)
        return StoredBlob(key=key, size_bytes=size, sha256=digest.hexdigest())

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
        target = self.path(key)
        if target.is_dir():
            shutil.rmtree(target, ignore_errors=True)
        else:
            target.unlink(missing_ok=True)

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
        folder = self.path(prefix)
        removed = 0
        for part in folder.glob("*/**/.*.part") if folder.is_dir() else ():
            try:
                if part.stat().st_mtime < older_than:
                    part.unlink(missing_ok=True)
                    removed += 1
            except FileNotFoundError:
                continue
        return removed

    def check(self) -> None:
        self.tmp_dir().rmdir()


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


def open_storage(settings: Settings) -> Storage:
    """The storage the settings name: the local folder ``resolved_storage_dir``."""
    return LocalStorage(settings.resolved_storage_dir)
