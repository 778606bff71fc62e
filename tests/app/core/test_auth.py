"""The auth service called directly: what a key row stores (no part of the secret), keys
limited to environments, the last-admin rule, the failed-key limiter, and the data
migration that replaces stored clear prefixes."""

from __future__ import annotations

import hashlib
import uuid
from pathlib import Path

import pytest
from alembic import command
from alembic.config import Config
from sqlalchemy import create_engine, select, text
from sqlalchemy.orm import Session, sessionmaker

from app import cli
from app.core import auth, environments
from app.core.enums import Scope
from app.core.errors import Conflict, Forbidden, InvalidInput, NotFound, TooManyRequests
from app.core.models import ApiKey
from tests.app.conftest import create_pg_database, drop_pg_database
from tests.conftest import REPO_ROOT

BOOTSTRAP = "my-own-bootstrap-admin-key-2026"


def test_bootstrap_key_stores_no_part_of_the_secret(session: Session) -> None:
    assert auth.bootstrap_admin_key(session, BOOTSTRAP)
    row = session.scalars(select(ApiKey)).one()
    # the clear start of a person-chosen key (10 of its 31 characters) was stored before
    assert row.prefix == "td_" + row.id[:8]
    for size in range(4, len(row.prefix) + 1):
        assert row.prefix[-size:] not in BOOTSTRAP and BOOTSTRAP[:size] not in row.prefix
    assert row.key_hash == hashlib.sha256(BOOTSTRAP.encode()).hexdigest()
    assert auth.authenticate(session, BOOTSTRAP, Scope.admin).key_id == row.id


def test_generated_token_starts_with_its_id_not_stored_secret(session: Session) -> None:
    row, token = auth.create_key(session, "station", ["capture"])
    assert row.prefix == "td_" + row.id[:8]
    secret = token.removeprefix(row.prefix + "_")
    assert len(secret) >= 43  # 256 random bits, url-safe base64
    assert secret[:6] not in row.prefix and secret not in str(row.__dict__)


def test_environment_limits(session: Session) -> None:
    one = environments.create(session, "one", ["a"], None, {}).id
    two = environments.create(session, "two", ["a"], None, {}).id
    _row, token = auth.create_key(session, "st", ["capture", "read"], environment_ids=[one])
    principal = auth.authenticate(session, token, Scope.read)
    assert principal.environment_ids == (one,)
    assert auth.can_reach(principal, one) and not auth.can_reach(principal, two)
    auth.require_environment(principal, one)
    with pytest.raises(NotFound, match=f"environment {two} not found"):
        auth.require_environment(principal, two)
    with pytest.raises(NotFound, match="snapshot s1 not found"):
        auth.require_environment(principal, two, detail="snapshot s1 not found")
    # jobs: its environment's jobs yes, other environments' 404, jobs of no environment 403
    auth.require_job_control(principal, "j", one)
    with pytest.raises(NotFound):
        auth.require_job_control(principal, "j", two)
    with pytest.raises(Forbidden):
        auth.require_job_control(principal, "j", None)
    _row, admin = auth.create_key(session, "adm", ["admin"])
    boss = auth.authenticate(session, admin, Scope.admin)
    assert boss.environment_ids is None and auth.can_reach(boss, two)
    auth.require_job_control(boss, "j", None)
    # a key limited to environments does not see the all-environment /metrics
    with pytest.raises(Forbidden):
        auth.authenticate(session, token, Scope.metrics)
    assert auth.authenticate(session, admin, Scope.metrics).key_id == boss.key_id


def test_create_key_refuses_bad_environment_lists(session: Session) -> None:
    env = environments.create(session, "one", ["a"], None, {}).id
    with pytest.raises(InvalidInput, match="admin"):
        auth.create_key(session, "x", ["admin"], environment_ids=[env])
    with pytest.raises(InvalidInput, match="unknown environment"):
        auth.create_key(session, "x", ["read"], environment_ids=[env, "nope"])
    with pytest.raises(InvalidInput):
        auth.create_key(session, "x", ["read"], environment_ids=[])
    row, _ = auth.create_key(session, "x", ["read"], environment_ids=[env, env])
    assert row.environment_ids == [env]


def test_last_admin_key_stays(session: Session) -> None:
    first, _ = auth.create_key(session, "a1", ["admin"])
    reader, _ = auth.create_key(session, "r", ["read"])
    with pytest.raises(Conflict) as info:
        auth.revoke(session, first)
    assert info.value.code == "LastAdminKey" and first.revoked_at is None
    auth.revoke(session, reader)
    second, _ = auth.create_key(session, "a2", ["admin"])
    auth.revoke(session, first)
    assert first.revoked_at is not None
    with pytest.raises(Conflict):
        auth.revoke(session, second)


def test_failed_key_limiter() -> None:
    now = [100.0]
    limiter = auth.FailedKeyLimiter(clock=lambda: now[0])
    for _ in range(3):
        limiter.check("10.0.0.1", limit=3, window_s=60)
        limiter.record_failure("10.0.0.1", limit=3, window_s=60)
    with pytest.raises(TooManyRequests) as info:
        limiter.check("10.0.0.1", limit=3, window_s=60)
    assert info.value.headers == {"Retry-After": "60"}
    limiter.check("10.0.0.2", limit=3, window_s=60)  # another address is not affected
    now[0] += 30.5
    with pytest.raises(TooManyRequests) as info:
        limiter.check("10.0.0.1", limit=3, window_s=60)
    assert info.value.headers == {"Retry-After": "30"}
    now[0] += 30
    limiter.check("10.0.0.1", limit=3, window_s=60)  # the window slid past the failures


def test_failed_key_limiter_memory_is_bounded() -> None:
    limiter = auth.FailedKeyLimiter(max_clients=100)
    for i in range(1000):
        limiter.record_failure(f"10.0.{i // 256}.{i % 256}", limit=5, window_s=60)
    assert limiter.tracked() <= 100


@pytest.mark.parametrize("dialect", ["sqlite", "postgres"])
def test_migration_replaces_stored_clear_prefixes(tmp_path: Path, dialect: str) -> None:
    name = f"twindelta_mig_{uuid.uuid4().hex[:8]}"
    url = create_pg_database(name) if dialect == "postgres" else f"sqlite:///{tmp_path / 'm.db'}"
    try:
        check_prefix_migration(url)
    finally:
        if dialect == "postgres":
            drop_pg_database(name)


def check_prefix_migration(url: str) -> None:
    config = Config(str(REPO_ROOT / "alembic.ini"))
    config.attributes["url"] = url
    command.upgrade(config, "0001")
    engine = create_engine(url)
    key_id = "0f1e2d3c-aaaa-4bbb-8ccc-123456789abc"
    with engine.begin() as conn:
        conn.execute(
            text(
                "INSERT INTO api_keys (id, name, prefix, key_hash, scopes, created_at) "
                "VALUES (:id, 'boot', :prefix, :hash, '[\"admin\"]', '2026-11-01 00:00:00')"
            ),
            {"id": key_id, "prefix": BOOTSTRAP[:10], "hash": "ab" * 32},
        )
    command.upgrade(config, "0002")
    with engine.connect() as conn:
        prefix, env_ids = conn.execute(text("SELECT prefix, environment_ids FROM api_keys")).one()
    assert prefix == "td_0f1e2d3c" and env_ids is None
    command.downgrade(config, "0001")
    with engine.connect() as conn:
        assert conn.execute(text("SELECT prefix FROM api_keys")).scalar() == "td_0f1e2d3c"
    engine.dispose()


def test_cli_creates_a_key_limited_to_environments(
    session_factory: sessionmaker[Session], capsys: pytest.CaptureFixture[str]
) -> None:
    with session_factory.begin() as s:
        env = environments.create(s, "one", ["a"], None, {}).id
    argv = ["create-key", "--scopes", "capture,read", "--environments", env]
    assert cli.main(argv) == 0
    token = capsys.readouterr().out.strip()
    with session_factory() as s:
        assert auth.authenticate(s, token, Scope.capture).environment_ids == (env,)
