"""Staging: each uploaded file is streamed in chunks into a private folder, within the byte
and file-count limits, and sorted by role (image, detections, cameras.json, classes.txt)
before anything is validated or stored."""

from __future__ import annotations

import fcntl
import hashlib
import os
import shutil
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import BinaryIO

from app.core.errors import (
    UnsupportedMedia,
)
from app.core.ingest.common import (
    _CONTROL,
    CAMERAS_NAME,
    CLASSES_NAME,
    IMAGE_SUFFIXES,
    LABEL_SUFFIX,
    _disk_full,
    _invalid,
    _no_space,
    _too_large,
)
from app.core.settings import Settings
from app.core.storage import Storage


@dataclass(frozen=True)
class UploadPart:
    """One uploaded file as the service sees it: the client's file name and a readable
    stream (a spooled temporary file; read in chunks, never whole)."""

    filename: str
    source: BinaryIO


@dataclass
class _Staged:
    path: Path
    where: str  # the name the client knows the file by (archive member or upload name)
    size: int
    sha256: str


@dataclass
class _Staging:
    """Files written to the staging folder so far, with the request's running totals."""

    root: Path
    settings: Settings
    images: dict[str, _Staged] = field(default_factory=dict)  # by file name
    image_stems: dict[str, str] = field(default_factory=dict)  # stem -> file name
    labels: dict[str, _Staged] = field(default_factory=dict)  # by stem
    cameras: _Staged | None = None
    classes: list[str] | None = None
    classes_sha256: str | None = None
    n_files: int = 0
    n_bytes: int = 0
    # Called with the current file's bytes so far, per chunk: an archive's inflation check.
    budget: Callable[[int], None] | None = None

    def digest(self) -> str:
        """SHA-256 over the sorted (stored name, content SHA-256) pairs: the same files give
        the same digest whether sent loose or in any archive."""
        entries = [(f"images/{n}", s.sha256) for n, s in self.images.items()]
        entries += [(f"labels/{stem}.txt", s.sha256) for stem, s in self.labels.items()]
        if self.cameras is not None:
            entries.append((CAMERAS_NAME, self.cameras.sha256))
        if self.classes_sha256 is not None:
            entries.append((CLASSES_NAME, self.classes_sha256))
        h = hashlib.sha256()
        for name, sha in sorted(entries):
            h.update(f"{name}\0{sha}\n".encode())
        return h.hexdigest()


def _file_name(raw: str, where: str) -> str:
    """The base name of an uploaded file; rejects empty, control characters, dot names."""
    name = raw.replace("\\", "/").rsplit("/", 1)[-1]
    if not name or name.startswith(".") or _CONTROL.search(name) or len(name.encode()) > 255:
        raise _invalid("InvalidFileName", f"{where}: {raw!r} is not a usable file name")
    return name


def _stage_file(staging: _Staging, kind: str, name: str, where: str, source: BinaryIO) -> _Staged:
    """Copy ``source`` into the staging folder in chunks, within the per-file and per-request
    byte limits and the file-count limit."""
    settings = staging.settings
    staging.n_files += 1
    if staging.n_files > settings.max_upload_files:
        raise _too_large(
            "TooManyFiles", f"{where}: more than {settings.max_upload_files} files in one upload"
        )
    remaining = settings.max_upload_bytes - staging.n_bytes
    limit = min(settings.max_file_bytes, remaining)
    target = staging.root / kind / name if kind else staging.root / name
    digest = hashlib.sha256()
    size = 0
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        with target.open("wb") as out:
            while chunk := source.read(1024 * 1024):
                size += len(chunk)
                if size > limit:
                    if limit == settings.max_file_bytes:
                        detail = f"{where}: larger than {settings.max_file_bytes} bytes"
                    else:
                        detail = (
                            f"{where}: the upload is larger than {settings.max_upload_bytes} bytes"
                        )
                    raise _too_large("PayloadTooLarge", detail)
                if staging.budget is not None:
                    staging.budget(size)
                digest.update(chunk)
                out.write(chunk)
    except OSError as exc:
        if _disk_full(exc):  # not the archive's fault: a clean 507, never "damaged"
            raise _no_space(where) from exc
        raise
    staging.n_bytes += size
    return _Staged(path=target, where=where, size=size, sha256=digest.hexdigest())


def _add(staging: _Staging, raw_name: str, where: str, source: BinaryIO, role: str | None) -> None:
    """Stage one file by its role (``images``, ``detections``, ``cameras``) or, for archive
    members (role None), by its name: images by suffix, ``cameras.json``, ``classes.txt``,
    other ``.txt`` files as detections."""
    name = _file_name(raw_name, where)
    lower = name.lower()
    suffix = PurePosixPath(lower).suffix
    if role == "detections" and lower == CLASSES_NAME:
        role = "classes"  # YOLO exports put classes.txt beside the labels
    if role is None:
        if lower == CAMERAS_NAME:
            role = "cameras"
        elif lower == CLASSES_NAME:
            role = "classes"
        elif suffix in IMAGE_SUFFIXES:
            role = "images"
        elif suffix == LABEL_SUFFIX:
            role = "detections"
        else:
            raise UnsupportedMedia(
                f"{where}: unsupported file type (images are .jpg .jpeg .png, detections .txt, "
                "plus optional cameras.json and classes.txt)",
                code="UnsupportedFileType",
            )
    if role == "images":
        if suffix not in IMAGE_SUFFIXES:
            raise UnsupportedMedia(
                f"{where}: images must be .jpg, .jpeg or .png", code="UnsupportedFileType"
            )
        stem = PurePosixPath(name).stem
        clash = staging.image_stems.get(stem)
        if clash is not None:
            raise _invalid(
                "DuplicateImage", f"{where}: another image ({clash}) has the same stem {stem!r}"
            )
        staging.image_stems[stem] = name
        staging.images[name] = _stage_file(staging, "images", name, where, source)
    elif role == "detections":
        if suffix != LABEL_SUFFIX:
            raise UnsupportedMedia(
                f"{where}: detections must be YOLO .txt files", code="UnsupportedFileType"
            )
        stem = PurePosixPath(name).stem
        if stem in staging.labels:
            raise _invalid("DuplicateDetections", f"{where}: a second detection file for {stem!r}")
        staging.labels[stem] = _stage_file(staging, "labels", f"{stem}.txt", where, source)
    elif role == "cameras":
        if staging.cameras is not None:
            raise _invalid("InvalidCameras", f"{where}: a second cameras.json")
        staging.cameras = _stage_file(staging, "", CAMERAS_NAME, where, source)
    else:  # classes.txt: checked against the environment, not stored
        if staging.classes_sha256 is not None:
            raise _invalid("ClassesMismatch", f"{where}: a second classes.txt")
        staged = _stage_file(staging, "", ".classes.txt", where, source)
        staging.classes_sha256 = staged.sha256


STAGING = ".tmp"
_STALE_UNLOCKED_S = 3600.0


@contextmanager
def _staging_dir(storage: Storage) -> Iterator[Path]:
    """A private staging folder ``.tmp/<id>``, removed on the way out. While it exists this
    process holds an exclusive ``flock`` on ``.tmp/<id>.lock``: the kernel drops the lock
    when the process dies, which is how :func:`sweep_staging` tells an abandoned folder (an
    API killed mid-upload) from one in use by another process."""
    base = storage.scratch_path(STAGING)
    name = uuid.uuid4().hex
    lock_path, root = base / f"{name}.lock", base / name
    try:
        base.mkdir(parents=True, exist_ok=True)
        fd = os.open(lock_path, os.O_CREAT | os.O_RDWR, 0o600)
    except OSError as exc:
        if _disk_full(exc):
            raise _no_space("upload") from exc
        raise
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        try:
            root.mkdir()
        except OSError as exc:
            if _disk_full(exc):
                raise _no_space("upload") from exc
            raise
        yield root
    finally:
        shutil.rmtree(root, ignore_errors=True)
        lock_path.unlink(missing_ok=True)
        os.close(fd)


def sweep_staging(storage: Storage) -> int:
    """Remove staging folders whose process is gone (their lock is free), and unlocked
    leftovers older than an hour; returns how many were removed. Safe beside live uploads
    in other processes: a held lock is never taken."""
    base = storage.scratch_path(STAGING)
    if not base.is_dir():
        return 0
    removed = 0
    for lock_path in base.glob("*.lock"):
        try:
            fd = os.open(lock_path, os.O_RDWR)
        except FileNotFoundError:
            continue
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                continue  # a live upload
            shutil.rmtree(base / lock_path.stem, ignore_errors=True)
            lock_path.unlink(missing_ok=True)
            removed += 1
        finally:
            os.close(fd)
    cutoff = time.time() - _STALE_UNLOCKED_S
    for folder in base.iterdir():
        if (
            folder.is_dir()
            and not (base / f"{folder.name}.lock").exists()
            and folder.stat().st_mtime < cutoff
        ):
            shutil.rmtree(folder, ignore_errors=True)
            removed += 1
    return removed
