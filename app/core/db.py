"""Engine and session factory. The edge (a request dependency or a task) owns the
transaction: ``with session_factory().begin() as session``; service functions never commit."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from functools import lru_cache
from typing import Any

from sqlalchemy import Engine, create_engine, event
from sqlalchemy.orm import DeclarativeBase, Session, sessionmaker

from app.core.settings import get_settings


class Base(DeclarativeBase):
    pass


READ_ONLY = "twindelta_read_only"


def make_engine(url: str) -> Engine:
    """An engine for ``url``; SQLite gets WAL, foreign keys and a busy timeout so the API
    and the worker processes can share the file."""
    if url.startswith("sqlite"):
        engine = create_engine(url, connect_args={"check_same_thread": False, "timeout": 30})

        @event.listens_for(engine, "connect")
        def _sqlite_pragmas(dbapi_connection: Any, _record: Any) -> None:
            # Let SQLAlchemy, not pysqlite, emit BEGIN: savepoints then work (SQLAlchemy
            # docs, "Serializable isolation / Savepoints / Transactional DDL").
            dbapi_connection.isolation_level = None
            cursor = dbapi_connection.cursor()
            cursor.execute("PRAGMA journal_mode=WAL")
            cursor.execute("PRAGMA foreign_keys=ON")
            cursor.execute("PRAGMA busy_timeout=30000")
            cursor.execute("PRAGMA synchronous=NORMAL")
            cursor.close()

        @event.listens_for(engine, "begin")
        def _sqlite_begin(conn: Any) -> None:
            # Writers take the write lock up front (BEGIN IMMEDIATE waits on busy_timeout);
            # a deferred transaction that reads and then writes can instead fail at once
            # when another process wrote in between. Readers stay deferred, so polling
            # never waits on a writer (WAL).
            read_only = conn.get_execution_options().get(READ_ONLY, False)
            conn.exec_driver_sql("BEGIN" if read_only else "BEGIN IMMEDIATE")

        return engine
    return create_engine(url, pool_pre_ping=True, pool_size=10, max_overflow=20)


@lru_cache(maxsize=1)
def get_engine() -> Engine:
    return make_engine(get_settings().resolved_database_url)


_session_factory: sessionmaker[Session] | None = None
_read_session_factory: sessionmaker[Session] | None = None
_override: sessionmaker[Session] | None = None


def get_session_factory() -> sessionmaker[Session]:
    """The process's session factory for transactions that may write."""
    global _session_factory
    if _override is not None:
        return _override
    if _session_factory is None:
        _session_factory = sessionmaker(bind=get_engine(), expire_on_commit=False)
    return _session_factory


def get_read_session_factory() -> sessionmaker[Session]:
    """A factory for read-only transactions (GET requests): on SQLite they never take the
    write lock; elsewhere it is the same as :func:`get_session_factory`."""
    global _read_session_factory
    if _override is not None:
        return _override
    if _read_session_factory is None:
        engine = get_engine().execution_options(**{READ_ONLY: True})
        _read_session_factory = sessionmaker(bind=engine, expire_on_commit=False)
    return _read_session_factory


def use_session_factory(factory: sessionmaker[Session] | None) -> None:
    """Bind the process to another factory for reads and writes (an embedding program, or a
    test's connection); None goes back to the settings' database."""
    global _override
    _override = factory


@contextmanager
def transaction() -> Iterator[Session]:
    """One short transaction for workers and scripts: commits on success, rolls back on error."""
    with get_session_factory().begin() as session:
        yield session
