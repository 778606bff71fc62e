"""Files derived from a stored cloud (its LAZ, its decimated levels), made once and stored
under their own key, so every host (and every later request) reuses them.

A derived file is made from the source's local copy under an exclusive ``flock`` on that
copy (one writer per cloud among this host's processes; whoever waited finds it made),
written to a part file in scratch and then moved in under its key (:meth:`Storage.move_in`:
a rename on the local folder, an upload that also leaves the file in this host's cache with
S3), so a reader never sees half a file.
"""

from __future__ import annotations

import errno
import fcntl
import shutil
from collections.abc import Callable
from pathlib import Path, PurePosixPath

from app.core.errors import Conflict, InsufficientStorage
from app.core.export.ply import PlyError
from app.core.storage import Storage


def is_fresh(storage: Storage, source_key: str, key: str) -> bool:
    """Whether ``key`` exists and was written no earlier than ``source_key``."""
    made = storage.modified_ns(key)
    if made is None:
        return False
    source = storage.modified_ns(source_key)
    return source is None or made >= source


def ensure_derived(
    storage: Storage, source_key: str, key: str, write: Callable[[Path, Path], object], what: str
) -> None:
    """Make ``key`` from ``source_key`` with ``write(source_path, part_path)`` unless an
    object at least as new as the source is there. ``what`` names it in errors ("the LAZ").
    FileNotFoundError when the source is missing; Conflict (409 ``PointCloudUnreadable``)
    when ``write`` raises PlyError; InsufficientStorage (507) when the disk is full."""
    if is_fresh(storage, source_key, key):
        return
    source = storage.local_file(source_key)
    staging = storage.tmp_dir()
    part = staging / PurePosixPath(key).name
    try:
        with source.open("rb") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            if not is_fresh(storage, source_key, key):
                write(source, part)
                storage.move_in(part, key)
    except PlyError as exc:
        raise Conflict(str(exc), code="PointCloudUnreadable") from exc
    except OSError as exc:
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):
            raise InsufficientStorage(
                f"the server's storage is full: {what} could not be written, try again later"
            ) from exc
        raise
    finally:
        shutil.rmtree(staging, ignore_errors=True)
