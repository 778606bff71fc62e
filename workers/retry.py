"""Transient database faults at the workers' edge.

A lock held past SQLite's busy timeout (``database is locked``) or a PostgreSQL restart
(connection refused, ``terminating connection due to administrator command``) says nothing
about the job: the same write succeeds a moment later. :func:`is_transient` tells those
apart from real errors, and :func:`retry_transient` retries a short transaction with
backoff up to a bound (``Settings.db_retry_s``).
"""

from __future__ import annotations

import logging
import sqlite3
import time
from collections.abc import Callable
from typing import TypeVar

from sqlalchemy.exc import DBAPIError, OperationalError

log = logging.getLogger(__name__)
T = TypeVar("T")

FIRST_DELAY_S = 0.2
MAX_DELAY_S = 5.0


def is_transient(exc: BaseException) -> bool:
    """True for a database error that a retry may clear: a lost or refused connection, or
    SQLite's lock timeout; False for everything else (a missing table, a bad statement)."""
    if isinstance(exc, DBAPIError) and exc.connection_invalidated:
        return True
    if not isinstance(exc, OperationalError):
        return False
    if isinstance(exc.orig, sqlite3.OperationalError):
        text = str(exc.orig).lower()
        return "locked" in text or "busy" in text
    return True  # psycopg's OperationalError: connection refused, closed, shut down, lock


def retry_transient(fn: Callable[[], T], *, bound_s: float, what: str) -> T:
    """``fn()``, called again with doubling waits (0.2 s up to 5 s) while it fails with a
    transient error and ``bound_s`` seconds have not passed; then the last error is raised."""
    deadline = time.monotonic() + bound_s
    delay = FIRST_DELAY_S
    while True:
        try:
            return fn()
        except Exception as exc:
            if not is_transient(exc) or time.monotonic() + delay > deadline:
                raise
            log.warning("%s: transient database error, retrying in %.1f s: %s", what, delay, exc)
        time.sleep(delay)
        delay = min(delay * 2, MAX_DELAY_S)
