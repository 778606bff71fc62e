"""Migration 0009 (external ids, snapshot-less seeds) on SQLite, where it rebuilds
``twin_instances`` and ``instance_poses``: the twin's rows survive the rebuild both ways,
the partial unique index holds, and a downgrade drops only what the old schema cannot hold
(instances and records seeded before any snapshot)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from alembic import command
from alembic.config import Config
from sqlalchemy import Connection, text
from sqlalchemy.exc import IntegrityError

from app.core.db import make_engine
from tests.conftest import REPO_ROOT

NOW = "2026-11-24 00:00:00"


def insert(conn: Connection, table: str, **values: Any) -> None:
    """A row of ``table`` with ``values`` and a placeholder in every other NOT NULL column
    that has no server default."""
    for _cid, name, kind, notnull, default, pk in conn.execute(
        text(f"PRAGMA table_info({table})")
    ).all():
        if name in values or not notnull or default is not None or pk:
            continue
        kind = str(kind).upper()
        if "INT" in kind or "BOOL" in kind or "FLOAT" in kind:
            values[name] = 0
        elif "DATE" in kind:
            values[name] = NOW
        elif "JSON" in kind:
            values[name] = "{}"
        else:
            values[name] = "x"
    columns = ", ".join(values)
    params = ", ".join(f":{k}" for k in values)
    conn.execute(text(f"INSERT INTO {table} ({columns}) VALUES ({params})"), values)


def count(conn: Connection, table: str) -> int:
    return int(conn.execute(text(f"SELECT count(*) FROM {table}")).scalar_one())


def test_0009_keeps_the_twin_and_its_downgrade_drops_only_snapshotless_seeds(
    tmp_path: Path,
) -> None:
    url = f"sqlite:///{tmp_path / 'm.db'}"
    config = Config(str(REPO_ROOT / "alembic.ini"))
    config.attributes["url"] = url
    command.upgrade(config, "0008")
    engine = make_engine(url)
    with engine.begin() as conn:
        insert(conn, "environments", id="e", name="cell", classes='["drill"]')
        insert(conn, "snapshots", id="s1", environment_id="e", seq=1, storage_prefix="p")
        insert(
            conn,
            "twin_instances",
            id="i1",
            environment_id="e",
            object_name="drill",
            since_snapshot_id="s1",
            created_snapshot_id="s1",
        )
        insert(
            conn, "instance_poses", id="r1", instance_id="i1", snapshot_id="s1", change_type="added"
        )
    engine.dispose()

    command.upgrade(config, "0009")
    engine = make_engine(url)
    with engine.begin() as conn:
        assert (count(conn, "twin_instances"), count(conn, "instance_poses")) == (1, 1)
        assert conn.execute(text("PRAGMA foreign_key_check")).all() == []
        conn.execute(text("UPDATE twin_instances SET external_id = 'A' WHERE id = 'i1'"))
        insert(
            conn,
            "twin_instances",
            id="i2",
            environment_id="e",
            object_name="drill",
            external_id="B",
        )  # seeded before any snapshot: no snapshot ids
        insert(conn, "instance_poses", id="r2", instance_id="i2", change_type="seeded")
        insert(conn, "instance_poses", id="r3", instance_id="i1", change_type="corrected")
    with pytest.raises(IntegrityError), engine.begin() as conn:
        insert(
            conn,
            "twin_instances",
            id="i3",
            environment_id="e",
            object_name="drill",
            external_id="A",
        )  # held by the open i1
    with engine.begin() as conn:  # a closed instance frees its id
        conn.execute(text("UPDATE twin_instances SET closed_snapshot_id = 's1' WHERE id = 'i1'"))
        insert(
            conn,
            "twin_instances",
            id="i3",
            environment_id="e",
            object_name="drill",
            external_id="A",
            created_snapshot_id="s1",
            since_snapshot_id="s1",
        )
    engine.dispose()

    command.downgrade(config, "0008")
    engine = make_engine(url)
    with engine.connect() as conn:
        ids = {r[0] for r in conn.execute(text("SELECT id FROM twin_instances"))}
        records = {r[0] for r in conn.execute(text("SELECT id FROM instance_poses"))}
        assert (ids, records) == ({"i1", "i3"}, {"r1"})
        columns = {r[1]: r[3] for r in conn.execute(text("PRAGMA table_info(twin_instances)"))}
        assert "external_id" not in columns and columns["created_snapshot_id"] == 1
    engine.dispose()
