"""twin instances carry the twin platform's external id (and adapter deliveries the twin id
they address); seeded instances need no snapshot

Revision ID: 0009
Revises: 0008
Create Date: 2026-11-24 13:00:00
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op


revision: str = "0009"
down_revision: str | None = "0008"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

_OPEN_WITH_ID = "closed_snapshot_id IS NULL AND external_id IS NOT NULL"


def upgrade() -> None:
    # SQLite rebuilds both tables (nullability); migrations/env.py turns foreign keys off
    # meanwhile, so instance_poses' ON DELETE CASCADE never fires.
    with op.batch_alter_table("twin_instances") as batch:
        batch.add_column(sa.Column("external_id", sa.String(length=200), nullable=True))
        batch.alter_column("since_snapshot_id", existing_type=sa.String(36), nullable=True)
        batch.alter_column("created_snapshot_id", existing_type=sa.String(36), nullable=True)
    with op.batch_alter_table("instance_poses") as batch:
        batch.alter_column("snapshot_id", existing_type=sa.String(36), nullable=True)
    with op.batch_alter_table("deliveries", recreate="never") as batch:
        batch.add_column(sa.Column("twin_id", sa.String(length=200), nullable=True))
    op.create_index(
        "uq_twin_instances_open_external_id",
        "twin_instances",
        ["environment_id", "external_id"],
        unique=True,
        postgresql_where=sa.text(_OPEN_WITH_ID),
        sqlite_where=sa.text(_OPEN_WITH_ID),
    )


def downgrade() -> None:
    # instances seeded before any snapshot (and records made then) have no snapshot to
    # belong to in the old schema: they are dropped
    op.drop_index("uq_twin_instances_open_external_id", table_name="twin_instances")
    with op.batch_alter_table("deliveries", recreate="never") as batch:
        batch.drop_column("twin_id")
    op.execute("DELETE FROM instance_poses WHERE snapshot_id IS NULL")
    op.execute(
        "DELETE FROM instance_poses WHERE instance_id IN"
        " (SELECT id FROM twin_instances WHERE created_snapshot_id IS NULL)"
    )
    op.execute("DELETE FROM twin_instances WHERE created_snapshot_id IS NULL")
    op.execute(
        "UPDATE twin_instances SET since_snapshot_id = created_snapshot_id"
        " WHERE since_snapshot_id IS NULL"
    )
    with op.batch_alter_table("instance_poses") as batch:
        batch.alter_column("snapshot_id", existing_type=sa.String(36), nullable=False)
    with op.batch_alter_table("twin_instances") as batch:
        batch.alter_column("created_snapshot_id", existing_type=sa.String(36), nullable=False)
        batch.alter_column("since_snapshot_id", existing_type=sa.String(36), nullable=False)
        batch.drop_column("external_id")
