"""Files derived from a stored cloud (its LAZ, its decimated levels), made once and cached.

A derived file is made under an exclusive ``flock`` on the source (one writer per cloud
among this host's processes; whoever waited finds it made), written to a part file and
renamed into place, so a reader never sees half a file.
"""

from __future__ import annotations

import errno
import fcntl
import os
import uuid
from collections.abc import Callable
from pathlib import Path

from app.core.errors import Conflict, InsufficientStorage
from app.core.export.ply import PlyError


def is_fresh(source: Path, target: Path) -> bool:
    """Whether ``target`` exists and is at least as new as ``source``."""
    return target.exists() and target.stat().st_mtime_ns >= source.stat().st_mtime_ns


def ensure_derived(source: Path, target: Path, write: Callable[[Path], object], what: str) -> None:
    """Make ``target`` from ``source`` with ``write(part_path)`` unless a file at least as
    new as ``source`` is there. ``what`` names it in errors ("the LAZ").
    Conflict (409 ``PointCloudUnreadable``) when ``write`` raises PlyError;
    InsufficientStorage (507) when the disk is full."""
    if is_fresh(source, target):
        return
    target.parent.mkdir(parents=True, exist_ok=True)
    part = target.with_name(f".{target.name}.{uuid.uuid4().hex}.part")
    try:
        with source.open("rb") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            if not is_fresh(source, target):
                write(part)
                os.replace(part, target)
    except PlyError as exc:
        raise Conflict(str(exc), code="PointCloudUnreadable") from exc
    except OSError as exc:
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):
            raise InsufficientStorage(
                f"the server's storage is full: {what} could not be written, try again later"
            ) from exc
        raise
    finally:
        part.unlink(missing_ok=True)
