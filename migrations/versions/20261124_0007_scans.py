"""laser scans as snapshots

Revision ID: 0007
Revises: 0006
Create Date: 2026-11-24 12:00:00
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0007"
down_revision: str | None = "0006"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    # photos: reconstructed from a capture; scan: read from an uploaded laser scan
    with op.batch_alter_table("snapshots") as batch:
        batch.add_column(
            sa.Column("source", sa.String(10), nullable=False, server_default="photos")
        )


def downgrade() -> None:
    with op.batch_alter_table("snapshots") as batch:
        batch.drop_column("source")
