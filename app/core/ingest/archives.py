"""Archives (.zip, .tar, .tar.gz): members are staged one by one, never trusting declared
sizes; member counts, inflation ratios (bombs), links and unsafe paths are refused."""

from __future__ import annotations

import re
import stat
import struct
import tarfile
import zipfile
import zlib
from pathlib import PurePosixPath
from typing import BinaryIO

from app.core.errors import (
    InvalidInput,
    PayloadTooLarge,
    UnsupportedMedia,
)
from app.core.ingest.common import _invalid, _reason, _too_large
from app.core.ingest.staging import UploadPart, _add, _Staging


def _unsafe(member: str, why: str) -> InvalidInput:
    return _invalid("UnsafeArchiveMember", f"archive member {member!r}: {why}")


def _member_path(name: str) -> PurePosixPath | None:
    """A safe relative member path, or None for entries to skip (folders, macOS extras)."""
    norm = name.replace("\\", "/")
    path = PurePosixPath(norm)
    if norm.startswith("/") or re.match(r"^[A-Za-z]:", norm):
        raise _unsafe(name, "absolute path")
    if ".." in path.parts:
        raise _unsafe(name, "path with '..'")
    if "\x00" in norm:
        raise _unsafe(name, "NUL in the name")
    if not path.parts or norm.endswith("/"):
        return None
    if "__MACOSX" in path.parts or path.name.startswith(".") or path.name == "Thumbs.db":
        return None
    return path


# Inflation allowed beyond ``max_archive_ratio`` × the compressed bytes: small archives of
# text (labels, tar headers) compress far better than photos.
ARCHIVE_SLACK_BYTES = 1024**2


def _bomb(where: str, inflated: int, packed: int, ratio: float) -> PayloadTooLarge:
    return _too_large(
        "ArchiveBomb",
        f"{where}: inflates to {inflated} bytes from {packed} compressed bytes, more than "
        f"{ratio:g} times (max_archive_ratio)",
    )


def _too_many_members(where: str, limit: int) -> PayloadTooLarge:
    return _too_large(
        "TooManyFiles", f"{where}: more than {limit} archive members (folders count too)"
    )


def _zip_entries(source: BinaryIO) -> int | None:
    """The member count the zip's end record declares, read before the central directory
    is parsed into memory; None when there is no readable end record."""
    try:
        end = zipfile._EndRecData(source)  # type: ignore[attr-defined]
    except (OSError, ValueError, struct.error):
        return None
    finally:
        source.seek(0)
    if not end:
        return None
    return int(end[zipfile._ECD_ENTRIES_TOTAL])  # type: ignore[attr-defined]


def _stage_zip(staging: _Staging, source: BinaryIO, where: str) -> None:
    settings = staging.settings
    declared_entries = _zip_entries(source)
    if declared_entries is not None and declared_entries > settings.max_archive_members:
        raise _too_many_members(where, settings.max_archive_members)
    try:
        archive = zipfile.ZipFile(source)
    except (zipfile.BadZipFile, OSError, ValueError) as exc:
        raise _invalid("InvalidArchive", f"{where}: not a readable zip ({_reason(exc)})") from exc
    with archive:
        infos = archive.infolist()
        if len(infos) > settings.max_archive_members:
            raise _too_many_members(where, settings.max_archive_members)
        files = [i for i in infos if not i.is_dir()]
        if len(files) > settings.max_upload_files:
            raise _too_large(
                "TooManyFiles",
                f"{where}: {len(files)} members, more than {settings.max_upload_files}",
            )
        declared = sum(i.file_size for i in files)
        if declared > settings.max_upload_bytes:
            raise _too_large(
                "PayloadTooLarge",
                f"{where}: unpacks to {declared} bytes, more than {settings.max_upload_bytes}",
            )
        # A member never inflates past its declared size (zipfile stops there and checks
        # the CRC), so the declared sizes bound what can be written: check them first.
        packed = sum(i.compress_size for i in files)
        if declared > settings.max_archive_ratio * packed + ARCHIVE_SLACK_BYTES:
            raise _bomb(where, declared, packed, settings.max_archive_ratio)
        for info in infos:
            mode = info.external_attr >> 16
            if mode and stat.S_IFMT(mode) not in (0, stat.S_IFREG, stat.S_IFDIR):
                raise _unsafe(info.filename, "not a regular file (link or device)")
            path = _member_path(info.filename)
            if path is None or info.is_dir():
                continue
            if info.flag_bits & 0x1:
                raise _invalid("InvalidArchive", f"{where}: member {info.filename!r} is encrypted")
            try:
                with archive.open(info) as member:
                    _add(staging, path.name, info.filename, member, None)  # type: ignore[arg-type]
            except (zipfile.BadZipFile, zlib.error, OSError, NotImplementedError) as exc:
                raise _invalid(
                    "InvalidArchive",
                    f"{where}: member {info.filename!r} is damaged ({_reason(exc)})",
                ) from exc


class _CountingReader:
    """Counts the bytes read from a stream: how much of a compressed archive was consumed."""

    def __init__(self, raw: BinaryIO) -> None:
        self.raw = raw
        self.n = 0

    def read(self, size: int = -1) -> bytes:
        data = self.raw.read(size)
        self.n += len(data)
        return data


def _stage_tar(staging: _Staging, source: BinaryIO, where: str) -> None:
    settings = staging.settings
    counted = _CountingReader(source)

    def budget(current: int) -> None:
        # Checked per chunk while extracting: stop at the limit, not after the bomb landed.
        inflated = staging.n_bytes + current
        if inflated > settings.max_archive_ratio * counted.n + ARCHIVE_SLACK_BYTES:
            raise _bomb(where, inflated, counted.n, settings.max_archive_ratio)

    staging.budget = budget
    try:
        with tarfile.open(fileobj=counted, mode="r|*") as archive:  # type: ignore[call-overload]
            for n_members, member in enumerate(archive, start=1):
                # Every member counts (folders too), and none is kept: a stream of headers
                # costs neither memory nor time without limit.
                archive.members = []
                if n_members > settings.max_archive_members:
                    raise _too_many_members(where, settings.max_archive_members)
                if not (member.isfile() or member.isdir()):
                    raise _unsafe(member.name, "not a regular file (link or device)")
                path = _member_path(member.name)
                if path is None or member.isdir():
                    continue
                extracted = archive.extractfile(member)
                if extracted is None:
                    raise _unsafe(member.name, "not a regular file")
                with extracted:
                    _add(staging, path.name, member.name, extracted, None)
    except (tarfile.TarError, EOFError, zlib.error, OSError) as exc:
        raise _invalid("InvalidArchive", f"{where}: not a readable tar ({_reason(exc)})") from exc
    finally:
        staging.budget = None


def _stage_archive(staging: _Staging, archive: UploadPart) -> None:
    where = archive.filename or "archive"
    lower = where.lower()
    if lower.endswith(".zip"):
        _stage_zip(staging, archive.source, where)
    elif lower.endswith((".tar", ".tar.gz", ".tgz")):
        _stage_tar(staging, archive.source, where)
    else:
        raise UnsupportedMedia(
            f"{where}: the archive must be .zip, .tar or .tar.gz", code="UnsupportedFileType"
        )
