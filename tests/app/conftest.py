"""Service test fixtures: a database built by the Alembic migrations (real PostgreSQL, and
SQLite for the embedded default), a rollback per test, an API client with keys per scope,
and a recorder of the tasks the code sends after commit."""

from __future__ import annotations

import os
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from alembic import command
from alembic.config import Config
from fastapi.testclient import TestClient
from sqlalchemy import Engine, create_engine, text
from sqlalchemy.orm import Session, sessionmaker

from app.core import auth, db, queue
from app.core.settings import get_settings
from app.main import create_app
from tests.conftest import REPO_ROOT

PG_ADMIN_URL = os.environ.get(
    "TWINDELTA_TEST_PG_URL", "postgresql+psycopg://postgres@127.0.0.1:5432/postgres"
)


def migrate(url: str) -> None:
    """Build a database the way production does: ``alembic upgrade head``."""
    config = Config(str(REPO_ROOT / "alembic.ini"))
    config.attributes["url"] = url
    command.upgrade(config, "head")


def create_pg_database(name: str) -> str:
    admin = create_engine(PG_ADMIN_URL, isolation_level="AUTOCOMMIT")
    with admin.connect() as conn:
        conn.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        conn.execute(text(f'CREATE DATABASE "{name}"'))
    admin.dispose()
    return PG_ADMIN_URL.rsplit("/", 1)[0] + f"/{name}"


def drop_pg_database(name: str) -> None:
    admin = create_engine(PG_ADMIN_URL, isolation_level="AUTOCOMMIT")
    with admin.connect() as conn:
        conn.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
    admin.dispose()


@pytest.fixture(scope="session", params=["postgres", "sqlite"])
def database_url(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[str]:
    """A migrated database: real PostgreSQL, and an SQLite file (the embedded default)."""
    if request.param == "postgres":
        name = f"twindelta_test_{uuid.uuid4().hex[:8]}"
        url = create_pg_database(name)
        migrate(url)
        yield url
        drop_pg_database(name)
    else:
        url = f"sqlite:///{tmp_path_factory.mktemp('sqlite') / 'twindelta.db'}"
        migrate(url)
        yield url


@pytest.fixture(scope="session")
def engine(database_url: str) -> Iterator[Engine]:
    eng = db.make_engine(database_url)
    yield eng
    eng.dispose()


@pytest.fixture
def data_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, database_url: str) -> Iterator[Path]:
    """Settings for one test: its own data folder, the test database, the embedded broker."""
    monkeypatch.setenv("TWINDELTA_DATA_DIR", str(tmp_path))
    monkeypatch.setenv("TWINDELTA_DATABASE_URL", database_url)
    monkeypatch.delenv("TWINDELTA_BROKER_URL", raising=False)
    get_settings.cache_clear()
    queue.get_sender.cache_clear()
    yield tmp_path
    get_settings.cache_clear()
    queue.get_sender.cache_clear()


@pytest.fixture
def session_factory(engine: Engine, data_dir: Path) -> Iterator[sessionmaker[Session]]:
    """Every session of the test (API requests, service calls) joins one outer transaction
    that is rolled back at the end, so tests never see each other's rows."""
    connection = engine.connect()
    outer = connection.begin()
    factory = sessionmaker(
        bind=connection, expire_on_commit=False, join_transaction_mode="create_savepoint"
    )
    db.use_session_factory(factory)
    yield factory
    db.use_session_factory(None)
    outer.rollback()
    connection.close()


@pytest.fixture
def session(session_factory: sessionmaker[Session]) -> Iterator[Session]:
    with session_factory() as s:
        yield s


@dataclass
class SentTasks:
    calls: list[tuple[str, dict[str, Any]]]

    def names(self) -> list[str]:
        return [name for name, _ in self.calls]


@pytest.fixture
def sent_tasks(monkeypatch: pytest.MonkeyPatch) -> SentTasks:
    """Record what is sent to the broker after commit instead of sending it."""
    sent = SentTasks(calls=[])
    monkeypatch.setattr(queue, "send_now", lambda name, **kw: sent.calls.append((name, kw)))
    return sent


@dataclass
class Keys:
    admin: str
    read: str
    capture: str

    def headers(self, which: str = "admin") -> dict[str, str]:
        return {"Authorization": f"Bearer {getattr(self, which)}"}


@pytest.fixture
def keys(session_factory: sessionmaker[Session]) -> Keys:
    with session_factory.begin() as s:
        tokens = {
            scope: auth.create_key(s, f"test {scope}", [scope])[1]
            for scope in ("admin", "read", "capture")
        }
    return Keys(**tokens)


@pytest.fixture
def client(session_factory: sessionmaker[Session], sent_tasks: SentTasks) -> Iterator[TestClient]:
    with TestClient(create_app()) as c:
        yield c
