"""The workers' glue (runner, tasks) runs against the same migrated databases as the service
tests: real PostgreSQL and the SQLite embedded default, a rollback per test."""

from __future__ import annotations

from tests.app.conftest import (  # noqa: F401  (fixtures)
    client,
    data_dir,
    database_url,
    engine,
    keys,
    sent_tasks,
    session,
    session_factory,
)
