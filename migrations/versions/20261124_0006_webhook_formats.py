"""webhook payload formats

Revision ID: 0006
Revises: 0005
Create Date: 2026-11-24 12:00:00

``webhook_subscriptions.format`` (existing subscriptions keep CloudEvents), and per delivery
the twin instance and rendered body of a platform adapter (Azure Digital Twins JSON Patch,
Eclipse Ditto merge patch; see app/core/webhooks/adapters.py).
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = '0006'
down_revision: str | None = '0005'
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("webhook_subscriptions") as batch:
        batch.add_column(
            sa.Column("format", sa.String(40), nullable=False, server_default="cloudevents")
        )
    with op.batch_alter_table("deliveries") as batch:
        batch.add_column(sa.Column("instance_id", sa.String(36), nullable=True))
        batch.add_column(sa.Column("payload", sa.JSON(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("deliveries") as batch:
        batch.drop_column("payload")
        batch.drop_column("instance_id")
    with op.batch_alter_table("webhook_subscriptions") as batch:
        batch.drop_column("format")
