"""Migration 0010 (the inventory: snapshot_objects, snapshots.inventory) on SQLite both ways:
existing snapshots keep their rows, an inventory row can be written and follows its
snapshot, and the downgrade drops only the inventory."""

from __future__ import annotations

from pathlib import Path

from alembic import command
from alembic.config import Config
from sqlalchemy import inspect, text

from app.core.db import make_engine
from tests.app.core.test_migration_0009 import count, insert
from tests.conftest import REPO_ROOT


def test_0010_upgrade_and_downgrade_on_sqlite(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'm.db'}"
    config = Config(str(REPO_ROOT / "alembic.ini"))
    config.attributes["url"] = url
    command.upgrade(config, "0009")
    engine = make_engine(url)
    with engine.begin() as conn:
        insert(conn, "environments", id="e", name="cell", classes='["drill"]')
        insert(conn, "snapshots", id="s1", environment_id="e", seq=1, storage_prefix="p")
    engine.dispose()
    command.upgrade(config, "0010")
    engine = make_engine(url)
    with engine.begin() as conn:
        assert conn.execute(text("SELECT inventory FROM snapshots")).scalar_one() is None
        insert(
            conn,
            "snapshot_objects",
            id="o1",
            snapshot_id="s1",
            position=0,
            object_name="drill",
            identification='{"metric": 0.8}',
            centroid_env="[0, 0, 0]",
        )
        assert count(conn, "snapshot_objects") == 1
        assert conn.execute(text("PRAGMA foreign_key_check")).all() == []
    engine.dispose()
    command.downgrade(config, "0009")
    engine = make_engine(url)
    with engine.connect() as conn:
        assert count(conn, "snapshots") == 1
        tables = inspect(conn).get_table_names()
        assert "snapshot_objects" not in tables
        assert "inventory" not in {c["name"] for c in inspect(conn).get_columns("snapshots")}
    engine.dispose()
