"""Alembic environment: the URL comes from the service settings (or ``-x url=...``), the
target metadata from app.core.models; SQLite runs in batch mode so ALTERs work there too."""

from __future__ import annotations

from alembic import context

from app.core import models  # noqa: F401  (registers every table on Base.metadata)
from app.core.db import Base, make_engine
from app.core.settings import get_settings

config = context.config
target_metadata = Base.metadata


def _url() -> str:
    return context.get_x_argument(as_dictionary=True).get("url") or (
        config.attributes.get("url") or get_settings().resolved_database_url
    )


def run_migrations_offline() -> None:
    context.configure(url=_url(), target_metadata=target_metadata, literal_binds=True)
    with context.begin_transaction():
        context.run_migrations()


def run_migrations_online() -> None:
    connection = config.attributes.get("connection")
    if connection is not None:
        _run(connection)
        return
    engine = make_engine(_url())
    with engine.connect() as conn:
        _run(conn)
    engine.dispose()


def _run(connection: object) -> None:
    sqlite = connection.dialect.name == "sqlite"  # type: ignore[attr-defined]
    if sqlite and not connection.in_transaction():  # type: ignore[attr-defined]
        # A batch ALTER rebuilds the table on SQLite (copy, drop, rename); with foreign keys
        # on, the drop would cascade to every row pointing at it. SQLite ignores this pragma
        # inside a transaction, so it goes to the driver before the migration's BEGIN.
        _driver(connection).execute("PRAGMA foreign_keys=OFF")
    try:
        _migrate(connection)
    finally:
        if sqlite and not connection.in_transaction():  # type: ignore[attr-defined]
            _driver(connection).execute("PRAGMA foreign_keys=ON")


def _driver(connection: object) -> object:
    return connection.connection.driver_connection  # type: ignore[attr-defined]


def _migrate(connection: object) -> None:
    context.configure(
        connection=connection,  # type: ignore[arg-type]
        target_metadata=target_metadata,
        render_as_batch=connection.dialect.name == "sqlite",  # type: ignore[attr-defined]
        compare_type=True,
    )
    with context.begin_transaction():
        context.run_migrations()


if context.is_offline_mode():
    run_migrations_offline()
else:
    run_migrations_online()
