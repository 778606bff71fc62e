"""Migration 0010 (the inventory: snapshot_objects, snapshots.inventory) on PostgreSQL and
SQLite, both ways: existing snapshots keep their rows, an inventory row can be written and
follows its snapshot, and the downgrade drops only the inventory."""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest
from alembic import command
from alembic.config import Config
from sqlalchemy import Engine, inspect, text

from app.core.db import make_engine
from tests.app.conftest import create_pg_database, drop_pg_database
from tests.app.core.test_migration_0009 import NOW, count
from tests.conftest import REPO_ROOT


@pytest.fixture(params=["postgres", "sqlite"])
def url(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[str]:
    if request.param == "sqlite":
        yield f"sqlite:///{tmp_path / 'm.db'}"
        return
    name = f"twindelta_m0010_{uuid.uuid4().hex[:8]}"
    yield create_pg_database(name)
    drop_pg_database(name)


def at_revision_with_environment(url: str, revision: str) -> tuple[Config, Engine]:
    """The database at ``url`` upgraded to ``revision`` with one environment ``e``: the
    Alembic config for further steps and an engine on it."""
    config = Config(str(REPO_ROOT / "alembic.ini"))
    config.attributes["url"] = url
    command.upgrade(config, revision)
    engine = make_engine(url)
    with engine.begin() as conn:
        conn.execute(
            text(
                "INSERT INTO environments (id, name, classes, reference, options, created_at)"
                " VALUES ('e', 'cell', '[\"drill\"]', NULL, '{}', :now)"
            ),
            {"now": NOW},
        )
    return config, engine


def test_0010_upgrade_and_downgrade(url: str) -> None:
    config, engine = at_revision_with_environment(url, "0009")
    with engine.begin() as conn:
        conn.execute(
            text(
                "INSERT INTO snapshots (id, environment_id, seq, state, source, storage_prefix,"
                " n_images, n_detections, upload_bytes, has_cameras, quality, created_at)"
                " VALUES ('s1', 'e', 1, 'reconstructed', 'photos', 'p', 0, 0, 0, false, '{}',"
                " :now)"
            ),
            {"now": NOW},
        )
    engine.dispose()
    command.upgrade(config, "0010")
    engine = make_engine(url)
    with engine.begin() as conn:
        assert conn.execute(text("SELECT inventory FROM snapshots")).scalar_one() is None
        conn.execute(
            text(
                "INSERT INTO snapshot_objects (id, snapshot_id, position, object_name,"
                " identification, centroid_env, created_at)"
                " VALUES ('o1', 's1', 0, 'drill', '{\"metric\": 0.8}', '[0, 0, 0]', :now)"
            ),
            {"now": NOW},
        )
        assert count(conn, "snapshot_objects") == 1
    with engine.begin() as conn:  # the inventory follows its snapshot
        conn.execute(text("DELETE FROM snapshots WHERE id = 's1'"))
        assert count(conn, "snapshot_objects") == 0
        conn.execute(
            text(
                "INSERT INTO snapshots (id, environment_id, seq, state, source, storage_prefix,"
                " n_images, n_detections, upload_bytes, has_cameras, quality, created_at)"
                " VALUES ('s2', 'e', 2, 'reconstructed', 'photos', 'p', 0, 0, 0, false, '{}',"
                " :now)"
            ),
            {"now": NOW},
        )
    engine.dispose()
    command.downgrade(config, "0009")
    engine = make_engine(url)
    with engine.connect() as conn:
        assert count(conn, "snapshots") == 1
        assert "snapshot_objects" not in inspect(conn).get_table_names()
        assert "inventory" not in {c["name"] for c in inspect(conn).get_columns("snapshots")}
    engine.dispose()
    command.upgrade(config, "head")
