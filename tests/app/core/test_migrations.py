"""The database the migrations build is the one the models describe."""

from __future__ import annotations

from pathlib import Path

from alembic import command
from alembic.autogenerate import compare_metadata
from alembic.config import Config
from alembic.migration import MigrationContext
from sqlalchemy import Engine, text

from app.core.db import Base, make_engine
from tests.conftest import REPO_ROOT


def test_models_and_migrations_agree(engine: Engine) -> None:
    with engine.connect() as conn:
        context = MigrationContext.configure(conn, opts={"compare_type": True})
        diff = compare_metadata(context, Base.metadata)
    assert diff == [], f"models and migrations differ: {diff}"


def test_sqlite_upgrade_keeps_rows_that_point_at_rebuilt_tables(tmp_path: Path) -> None:
    """A batch migration that rebuilds a table on SQLite drops the old one; with foreign keys
    on, ON DELETE CASCADE would take every row pointing at it (0003 rebuilds
    webhook_subscriptions: its deliveries were lost). Rows must survive head and back."""
    url = f"sqlite:///{tmp_path / 'upgrade.db'}"
    config = Config(str(REPO_ROOT / "alembic.ini"))
    config.attributes["url"] = url
    command.upgrade(config, "0002")
    engine = make_engine(url)
    now = "2026-11-24 00:00:00"
    with engine.begin() as conn:
        conn.execute(
            text(
                "INSERT INTO webhook_subscriptions (id, url, secret, event_types, active,"
                " created_at) VALUES ('s1', 'https://example.com/hook', 'whsec_abc', '[]', 1,"
                " :now)"
            ),
            {"now": now},
        )
        conn.execute(
            text(
                "INSERT INTO events (id, type, subject, data, created_at)"
                " VALUES ('e1', 'job.failed', 'jobs/x', '{}', :now)"
            ),
            {"now": now},
        )
        conn.execute(
            text(
                "INSERT INTO deliveries (id, subscription_id, event_id, ordering_key, seq, state,"
                " attempts, run_attempts, created_at)"
                " VALUES ('d1', 's1', 'e1', 'k', 1, 'pending', 0, 0, :now)"
            ),
            {"now": now},
        )
    engine.dispose()
    command.upgrade(config, "head")
    engine = make_engine(url)
    with engine.connect() as conn:
        assert conn.execute(text("SELECT count(*) FROM deliveries")).scalar_one() == 1
        assert conn.execute(text("PRAGMA foreign_key_check")).all() == []
    engine.dispose()
    command.downgrade(config, "0002")
    engine = make_engine(url)
    with engine.connect() as conn:
        assert conn.execute(text("SELECT count(*) FROM deliveries")).scalar_one() == 1
    engine.dispose()
