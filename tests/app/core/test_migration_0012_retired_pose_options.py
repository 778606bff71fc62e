"""Migration 0012 (retired pose options) on PostgreSQL and SQLite: ``max_rmse_voxels`` is
dropped from every ``"pose"`` section of the stored option documents, and nothing else
changes, so a stored override cannot fail later jobs as an unknown option."""

from __future__ import annotations

import json

from alembic import command
from sqlalchemy import text

from app.core.db import make_engine
from app.core.options import check_environment_options
from tests.app.core.test_migration_0009 import NOW
from tests.app.core.test_migration_0010_inventory import (  # noqa: F401 (the fixture)
    at_revision_with_environment,
    url,
)

OLD_OPTIONS = {
    "compare": {"preset": "default", "pose": {"max_rmse_voxels": 0.4, "min_fitness": 0.3}},
    "inventory": {"pose": {"max_rmse_voxels": 0.4}, "band_sigmas": 3.0},
    "retention": {"images_after_days": 30},
}
KEPT = {
    "compare": {"preset": "default", "pose": {"min_fitness": 0.3}},
    "inventory": {"pose": {}, "band_sigmas": 3.0},
    "retention": {"images_after_days": 30},
}


def test_0012_drops_the_retired_pose_option_and_nothing_else(url: str) -> None:  # noqa: F811
    config, engine = at_revision_with_environment(url, "0011")
    with engine.begin() as conn:
        conn.execute(
            text("UPDATE environments SET options = :o WHERE id = 'e'"),
            {"o": json.dumps(OLD_OPTIONS)},
        )
        for job_id, options in (("j1", OLD_OPTIONS["compare"]), ("j2", {"max_rmse_voxels": 1})):
            conn.execute(
                text(
                    "INSERT INTO jobs (id, kind, task_name, state, progress, preset, options,"
                    " result, cancel_requested, attempts, sends, environment_id, created_at)"
                    " VALUES (:id, 'compare', 't', 'queued', 0, 'default', :o, '{}', false, 0,"
                    " 0, 'e', :now)"
                ),
                {"id": job_id, "o": json.dumps(options), "now": NOW},
            )
    engine.dispose()
    command.upgrade(config, "0012")
    engine = make_engine(url)
    with engine.connect() as conn:
        env = conn.execute(text("SELECT options FROM environments WHERE id = 'e'")).scalar_one()
        jobs = dict(conn.execute(text("SELECT id, options FROM jobs")).all())
    engine.dispose()
    loaded = {k: json.loads(v) if isinstance(v, str) else v for k, v in jobs.items()}
    env = json.loads(env) if isinstance(env, str) else env
    assert env == KEPT
    check_environment_options(env)  # what the upgrade left is valid to the new code
    assert loaded == {"j1": KEPT["compare"], "j2": {"max_rmse_voxels": 1}}  # not a pose section
    command.downgrade(config, "0011")
    command.upgrade(config, "head")
