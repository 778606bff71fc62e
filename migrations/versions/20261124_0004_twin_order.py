"""twin updates applied per environment in snapshot order

Revision ID: 0004
Revises: 0003
Create Date: 2026-11-24 00:45:00
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op


revision: str = '0004'
down_revision: str | None = '0003'
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    # Plain ADD COLUMNs only (recreate='never'): on SQLite a batch that recreated
    # ``environments`` would DROP it, and with foreign keys on that deletes every snapshot,
    # job and comparison through their ON DELETE CASCADE. A constant string server default
    # keeps ``twin_seq`` an ADD COLUMN there.
    with op.batch_alter_table('environments', recreate='never') as batch:
        batch.add_column(sa.Column('twin_seq', sa.Integer(), nullable=False, server_default='0'))
        batch.add_column(sa.Column('twin_snapshot_id', sa.String(length=36), nullable=True))
        batch.add_column(sa.Column('twin_blocked_by', sa.String(length=36), nullable=True))
    with op.batch_alter_table('snapshots', recreate='never') as batch:
        batch.add_column(sa.Column('twin_update', sa.String(length=20), nullable=True))
    with op.batch_alter_table('comparisons', recreate='never') as batch:
        batch.add_column(sa.Column('applied_at', sa.DateTime(timezone=True), nullable=True))
    with op.batch_alter_table('changes', recreate='never') as batch:
        batch.add_column(sa.Column('object_id', sa.String(length=36), nullable=True))
        batch.add_column(sa.Column('replaced_instance_id', sa.String(length=36), nullable=True))
        batch.add_column(sa.Column('centroid_env', sa.JSON(), nullable=True))
    _settle_existing()


def _settle_existing() -> None:
    """Existing environments: the twin has taken into account every snapshot of the longest
    run, from seq 1, of snapshots that are final and (when reconstructed after the first)
    whose automatic comparison was applied; the chain goes on from there."""
    bind = op.get_bind()
    envs = sa.table('environments', sa.column('id'), sa.column('twin_seq'),
                    sa.column('twin_snapshot_id'))
    snaps = sa.table('snapshots', sa.column('id'), sa.column('environment_id'),
                     sa.column('seq'), sa.column('state'), sa.column('twin_update'))
    comps = sa.table('comparisons', sa.column('id'), sa.column('after_id'),
                     sa.column('automatic'), sa.column('applied_to_state'),
                     sa.column('completed_at'), sa.column('applied_at'))
    applied = {
        row.after_id: row.id
        for row in bind.execute(
            sa.select(comps.c.id, comps.c.after_id).where(
                comps.c.automatic.is_(True), comps.c.applied_to_state.is_(True)
            )
        )
    }
    for (env_id,) in bind.execute(sa.select(envs.c.id)).all():
        seq, base = 0, None
        rows = bind.execute(
            sa.select(snaps.c.id, snaps.c.seq, snaps.c.state)
            .where(snaps.c.environment_id == env_id)
            .order_by(snaps.c.seq)
        ).all()
        for snap_id, snap_seq, state in rows:
            if state in ('failed', 'cancelled'):
                outcome = 'skipped'
            elif state == 'reconstructed' and base is None:
                outcome = 'baseline'
            elif state == 'reconstructed' and snap_id in applied:
                outcome = 'applied'
                bind.execute(
                    comps.update()
                    .where(comps.c.id == applied[snap_id])
                    .values(applied_at=comps.c.completed_at)
                )
            else:
                break
            if outcome != 'skipped':
                base = snap_id
            seq = snap_seq
            bind.execute(snaps.update().where(snaps.c.id == snap_id).values(twin_update=outcome))
        bind.execute(
            envs.update().where(envs.c.id == env_id).values(twin_seq=seq, twin_snapshot_id=base)
        )


def downgrade() -> None:
    # ALTER TABLE ... DROP COLUMN (SQLite 3.35+), never a recreate: see upgrade()
    with op.batch_alter_table('changes', recreate='never') as batch:
        batch.drop_column('centroid_env')
        batch.drop_column('replaced_instance_id')
        batch.drop_column('object_id')
    with op.batch_alter_table('comparisons', recreate='never') as batch:
        batch.drop_column('applied_at')
    with op.batch_alter_table('snapshots', recreate='never') as batch:
        batch.drop_column('twin_update')
    with op.batch_alter_table('environments', recreate='never') as batch:
        batch.drop_column('twin_blocked_by')
        batch.drop_column('twin_snapshot_id')
        batch.drop_column('twin_seq')
