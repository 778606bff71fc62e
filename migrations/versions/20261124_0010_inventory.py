"""the inventory of every snapshot: the library objects it shows (snapshot_objects) and its
summary (snapshots.inventory)

Revision ID: 0010
Revises: 0009
Create Date: 2026-11-24 15:00:00
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

from app.core.models import _UtcDateTime

revision: str = "0010"
down_revision: str | None = "0009"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_table(
        "snapshot_objects",
        sa.Column("id", sa.String(length=36), primary_key=True),
        sa.Column(
            "snapshot_id",
            sa.String(length=36),
            sa.ForeignKey("snapshots.id", ondelete="CASCADE"),
            nullable=False,
        ),
        sa.Column("position", sa.Integer(), nullable=False),
        sa.Column("object_name", sa.String(length=200), nullable=False),
        sa.Column(
            "object_id",
            sa.String(length=36),
            sa.ForeignKey("library_objects.id", ondelete="SET NULL"),
            nullable=True,
        ),
        sa.Column("pose", sa.JSON(), nullable=True),
        sa.Column("pose_quality", sa.JSON(), nullable=True),
        sa.Column("identification", sa.JSON(), nullable=False),
        sa.Column("centroid_env", sa.JSON(), nullable=False),
        sa.Column("support", sa.String(length=50), nullable=True),
        sa.Column(
            "instance_id",
            sa.String(length=36),
            sa.ForeignKey("twin_instances.id", ondelete="SET NULL"),
            nullable=True,
        ),
        sa.Column("created_at", _UtcDateTime(), nullable=False),
    )
    op.create_index("ix_snapshot_objects_snapshot_id", "snapshot_objects", ["snapshot_id"])
    op.create_index("ix_snapshot_objects_instance_id", "snapshot_objects", ["instance_id"])
    # a plain ADD COLUMN on both databases (nullable, no constraint): no table rebuild
    with op.batch_alter_table("snapshots", recreate="never") as batch:
        batch.add_column(sa.Column("inventory", sa.JSON(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("snapshots", recreate="never") as batch:
        batch.drop_column("inventory")
    op.drop_index("ix_snapshot_objects_instance_id", table_name="snapshot_objects")
    op.drop_index("ix_snapshot_objects_snapshot_id", table_name="snapshot_objects")
    op.drop_table("snapshot_objects")
