"""Snapshots: one uploaded capture of an environment and what reconstruction made of it.
(Uploads themselves are validated and stored by :mod:`app.core.ingest`.)"""

from __future__ import annotations

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.core.enums import JobKind, SnapshotState
from app.core.errors import NotFound
from app.core.models import Comparison, Job, Snapshot


def get(session: Session, snapshot_id: str) -> Snapshot:
    snap = session.get(Snapshot, snapshot_id)
    if snap is None or snap.state == SnapshotState.deleted:  # a tombstone (app/core/retention)
        raise NotFound(f"snapshot {snapshot_id} not found")
    return snap


def history(session: Session, environment_id: str) -> list[Snapshot]:
    """Every snapshot of an environment, newest first (deleted ones are left out)."""
    return list(
        session.scalars(
            select(Snapshot)
            .where(
                Snapshot.environment_id == environment_id,
                Snapshot.state != SnapshotState.deleted,
            )
            .order_by(Snapshot.seq.desc())
        ).all()
    )


def latest_reconstructed_before(session: Session, snapshot: Snapshot) -> Snapshot | None:
    """The newest earlier snapshot of the same environment that was reconstructed."""
    return session.scalar(
        select(Snapshot)
        .where(
            Snapshot.environment_id == snapshot.environment_id,
            Snapshot.seq < snapshot.seq,
            Snapshot.state == SnapshotState.reconstructed,
        )
        .order_by(Snapshot.seq.desc())
        .limit(1)
    )


def job_of(session: Session, snapshot_id: str) -> Job | None:
    return session.scalar(
        select(Job)
        .where(Job.snapshot_id == snapshot_id, Job.kind == JobKind.snapshot)
        .order_by(Job.created_at.desc())
        .limit(1)
    )


def automatic_comparison_of(session: Session, snapshot_id: str) -> Comparison | None:
    return session.scalar(
        select(Comparison)
        .where(Comparison.after_id == snapshot_id, Comparison.automatic.is_(True))
        .order_by(Comparison.created_at.desc())
        .limit(1)
    )
