"""api keys limited to environments, non-secret key ids

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-24 00:45:00
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op


revision: str = '0002'
down_revision: str | None = '0001'
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("api_keys") as batch:
        batch.add_column(sa.Column("environment_ids", sa.JSON(), nullable=True))
    # The stored prefix used to be the token's first 10 characters: for a person-chosen
    # bootstrap key that was most of the secret in the clear. Replace every one with the
    # non-secret id the code now stores ("td_" + the first 8 hex digits of the row id).
    op.execute(sa.text("UPDATE api_keys SET prefix = 'td_' || substr(id, 1, 8)"))


def downgrade() -> None:
    # The old clear prefixes are gone on purpose; the non-secret ids stay.
    with op.batch_alter_table("api_keys") as batch:
        batch.drop_column("environment_ids")
