"""webhook secrets encrypted at rest, secret rotation

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-24 00:45:00

``secret`` (plain ``whsec_...``) becomes ``secret_encrypted`` (a Fernet token, see
app/core/secretbox.py; the key comes from the settings: TWINDELTA_SECRET_KEY, or the key file
the embedded default generates under the data folder), and the rotation columns are added.
Existing secrets are encrypted here; the downgrade decrypts them back.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = '0003'
down_revision: str | None = '0002'
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

_subs = sa.table(
    "webhook_subscriptions",
    sa.column("id", sa.String),
    sa.column("secret", sa.String),
    sa.column("secret_encrypted", sa.String),
)


def _settings():  # type: ignore[no-untyped-def]
    from app.core.settings import get_settings

    return get_settings()


def upgrade() -> None:
    from app.core import secretbox

    with op.batch_alter_table("webhook_subscriptions") as batch:
        batch.alter_column(
            "secret",
            new_column_name="secret_encrypted",
            existing_type=sa.String(200),
            type_=sa.String(500),
            existing_nullable=False,
        )
        batch.add_column(sa.Column("previous_secret_encrypted", sa.String(500), nullable=True))
        batch.add_column(
            sa.Column("previous_secret_expires_at", sa.DateTime(timezone=True), nullable=True)
        )
    bind = op.get_bind()
    rows = bind.execute(sa.select(_subs.c.id, _subs.c.secret_encrypted)).all()
    plain = [(i, s) for i, s in rows if not s.startswith(secretbox.TOKEN_PREFIX)]
    if plain:  # the key is only needed (and, embedded, generated) when there is a secret
        settings = _settings()
        for sub_id, secret in plain:
            bind.execute(
                _subs.update()
                .where(_subs.c.id == sub_id)
                .values(secret_encrypted=secretbox.encrypt(settings, secret))
            )


def downgrade() -> None:
    from app.core import secretbox

    bind = op.get_bind()
    rows = bind.execute(sa.select(_subs.c.id, _subs.c.secret_encrypted)).all()
    tokens = [(i, s) for i, s in rows if s.startswith(secretbox.TOKEN_PREFIX)]
    if tokens:
        settings = _settings()
        for sub_id, token in tokens:
            bind.execute(
                _subs.update()
                .where(_subs.c.id == sub_id)
                .values(secret_encrypted=secretbox.decrypt(settings, token))
            )
    with op.batch_alter_table("webhook_subscriptions") as batch:
        batch.drop_column("previous_secret_expires_at")
        batch.drop_column("previous_secret_encrypted")
        batch.alter_column(
            "secret_encrypted",
            new_column_name="secret",
            existing_type=sa.String(500),
            type_=sa.String(200),
            existing_nullable=False,
        )
