"""resumable uploads kept as stored parts: offset, part names and the finisher's heartbeat
on the row, so any API host can take the next PATCH. Uploads under way at the upgrade kept
their bytes in one host's partial file; they expire now (clients start them again).

Revision ID: 0011
Revises: 0010
Create Date: 2026-11-24 16:00:00
"""

from collections.abc import Sequence
from datetime import UTC, datetime

import sqlalchemy as sa
from alembic import op

from app.core.models import _UtcDateTime

revision: str = "0011"
down_revision: str | None = "0010"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("resumable_uploads") as batch:
        batch.add_column(
            sa.Column("offset_bytes", sa.BigInteger(), nullable=False, server_default="0")
        )
        batch.add_column(sa.Column("parts", sa.JSON(), nullable=False, server_default="[]"))
        batch.add_column(sa.Column("heartbeat_at", _UtcDateTime(), nullable=True))
    op.execute(
        sa.text(
            "UPDATE resumable_uploads SET expires_at = :now"
            " WHERE state IN ('receiving', 'processing') AND expires_at > :now"
        ).bindparams(sa.bindparam("now", datetime.now(UTC), type_=_UtcDateTime()))
    )


def downgrade() -> None:
    with op.batch_alter_table("resumable_uploads") as batch:
        batch.drop_column("heartbeat_at")
        batch.drop_column("parts")
        batch.drop_column("offset_bytes")
