"""Migration 0011 (resumable uploads kept as stored parts: offset_bytes, parts, heartbeat_at)
on PostgreSQL and SQLite, both ways: uploads under way expire (their bytes were one host's
partial file, which the new code cannot read), ended ones keep their expiry, and the
downgrade drops only the new columns."""

from __future__ import annotations

from datetime import UTC, datetime

from alembic import command
from sqlalchemy import inspect, text

from app.core.db import make_engine
from tests.app.core.test_migration_0009 import NOW, count
from tests.app.core.test_migration_0010_inventory import (  # noqa: F401 (the fixture)
    at_revision_with_environment,
    url,
)

LATER = "2099-01-01 00:00:00"


def test_0011_upgrade_expires_uploads_under_way_and_downgrades(url: str) -> None:  # noqa: F811
    config, engine = at_revision_with_environment(url, "0010")
    with engine.begin() as conn:
        for upload_id, state in (("u1", "receiving"), ("u2", "processing"), ("u3", "completed")):
            conn.execute(
                text(
                    "INSERT INTO resumable_uploads (id, environment_id, state, length, filename,"
                    " storage_key, created_at, expires_at) VALUES (:id, 'e', :state, 10,"
                    " 'a.zip', :key, :now, :later)"
                ),
                {"id": upload_id, "state": state, "key": f"uploads/{upload_id}", "now": NOW,
                 "later": LATER},
            )  # fmt: skip
    engine.dispose()
    before = datetime.now(UTC)
    command.upgrade(config, "0011")
    engine = make_engine(url)
    with engine.connect() as conn:
        rows = {
            r.id: r
            for r in conn.execute(
                text("SELECT id, expires_at, offset_bytes, parts FROM resumable_uploads")
            )
        }
    assert {r.offset_bytes for r in rows.values()} == {0}
    for upload_id in ("u1", "u2"):
        expires = rows[upload_id].expires_at
        expires = datetime.fromisoformat(expires) if isinstance(expires, str) else expires
        assert expires.replace(tzinfo=expires.tzinfo or UTC) <= datetime.now(UTC)
        assert expires.replace(tzinfo=expires.tzinfo or UTC) >= before.replace(microsecond=0)
    assert str(rows["u3"].expires_at).startswith("2099-01-01")
    engine.dispose()
    command.downgrade(config, "0010")
    engine = make_engine(url)
    with engine.connect() as conn:
        assert count(conn, "resumable_uploads") == 3
        columns = {c["name"] for c in inspect(conn).get_columns("resumable_uploads")}
        assert not columns & {"offset_bytes", "parts", "heartbeat_at"}
    engine.dispose()
    command.upgrade(config, "head")
