"""What every part of ingest shares: file names and suffixes, and the errors a client sees
(each names the file and, for text, the line; never a server path)."""

from __future__ import annotations

import errno
import re

from app.core.errors import (
    InsufficientStorage,
    InvalidInput,
    PayloadTooLarge,
)

TASK = "snapshot.process"
IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png"}
IMAGE_FORMATS = {"JPEG", "PNG"}
LABEL_SUFFIX = ".txt"
CAMERAS_NAME = "cameras.json"
CLASSES_NAME = "classes.txt"
CAMERAS_MAX_BYTES = 32 * 1024**2
_SEQ_RETRIES = 5
_CONTROL = re.compile(r"[\x00-\x1f\x7f]")


def _invalid(code: str, detail: str) -> InvalidInput:
    return InvalidInput(detail, code=code)


def _too_large(code: str, detail: str) -> PayloadTooLarge:
    return PayloadTooLarge(detail, code=code)


_SERVER_PATH = re.compile(
    r"<_io\.\w+ name=(?:'[^']*'|\"[^\"]*\"|\S+?)>|(?<![\w.])/(?:[^\s/'\"<>:]+/)+[^\s/'\"<>:]*"
)


def _reason(exc: BaseException) -> str:
    """An exception's message for a client: server paths removed (never show them)."""
    text = _SERVER_PATH.sub("the file", str(exc)).strip()
    return text or type(exc).__name__


def _disk_full(exc: OSError) -> bool:
    return exc.errno in (errno.ENOSPC, errno.EDQUOT)


def _no_space(where: str) -> InsufficientStorage:
    return InsufficientStorage(
        f"{where}: the server's storage is full; nothing of this upload was kept, try again later"
    )
