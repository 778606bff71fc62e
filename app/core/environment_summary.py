"""What an environment list shows besides the environment: how many objects its twin holds
and its newest snapshot (two queries for any number of environments)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from app.core.enums import SnapshotState
from app.core.models import Snapshot, TwinInstance


@dataclass(frozen=True)
class LastSnapshot:
    id: str
    seq: int
    state: str
    created_at: datetime


@dataclass(frozen=True)
class Summary:
    """``twin_object_count``: the twin's open instances; ``last_snapshot``: the newest
    snapshot not deleted (None before any)."""

    twin_object_count: int
    last_snapshot: LastSnapshot | None


def summaries(session: Session, environment_ids: Sequence[str]) -> dict[str, Summary]:
    """The summary of each of ``environment_ids``."""
    ids = list(environment_ids)
    if not ids:
        return {}
    counts = dict(
        session.execute(
            select(TwinInstance.environment_id, func.count())
            .where(TwinInstance.environment_id.in_(ids), TwinInstance.closed_snapshot_id.is_(None))
            .group_by(TwinInstance.environment_id)
        ).all()
    )
    newest = (
        select(Snapshot.environment_id, func.max(Snapshot.seq).label("seq"))
        .where(Snapshot.environment_id.in_(ids), Snapshot.state != SnapshotState.deleted)
        .group_by(Snapshot.environment_id)
        .subquery()
    )
    last = {
        row.environment_id: LastSnapshot(row.id, row.seq, str(row.state), row.created_at)
        for row in session.execute(
            select(
                Snapshot.environment_id,
                Snapshot.id,
                Snapshot.seq,
                Snapshot.state,
                Snapshot.created_at,
            ).join(
                newest,
                (Snapshot.environment_id == newest.c.environment_id)
                & (Snapshot.seq == newest.c.seq),
            )
        )
    }
    return {i: Summary(int(counts.get(i, 0)), last.get(i)) for i in ids}
