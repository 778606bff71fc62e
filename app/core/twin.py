"""The twin's state: instances of library objects in an environment, with pose history,
brought forward one snapshot at a time in ``seq`` order.

The chain (:func:`advance`) walks an environment's snapshots from the last one the twin took
into account (``Environment.twin_seq``), holding the environment row locked so that two
workers never move it at once:

    next snapshot uploaded / processing        ──▶ wait for it (never compared past)
    next snapshot failed / cancelled / deleted ──▶ skipped, on the record (twin.updated)
    next snapshot reconstructed, the first one ──▶ the baseline (twin.updated)
    otherwise its automatic comparison with the snapshot the twin reflects
        (``Environment.twin_snapshot_id``):
        none yet              ──▶ created and queued; wait for it
        queued / running      ──▶ wait for it
        succeeded             ──▶ its changes applied (twin.updated); go on
        failed / cancelled    ──▶ blocked (twin.blocked) until it is retried

An automatic comparison is therefore created only once every earlier snapshot is settled:
its "before" is decided by seq order, not by which job finished first, and the twin it
reads is the twin as it stood after that snapshot. Whoever changes what the chain waits on
(a reconstruction, a comparison, a failed or cancelled job, a retry) calls :func:`advance`
in the same transaction.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

from sqlalchemy import func, or_, select
from sqlalchemy.orm import Session, aliased

from app.core import comparisons, events, inventory
from app.core.enums import (
    ChangeType,
    ComparisonState,
    EventType,
    JobKind,
    JobState,
    SnapshotState,
    TwinStatus,
    TwinUpdate,
)
from app.core.errors import NotFound
from app.core.models import (
    Comparison,
    Environment,
    InstancePose,
    Job,
    Snapshot,
    TwinInstance,
    new_id,
    utcnow,
)
from app.core.twin_records import changed_instances, inventoried_instances, open_instances

log = logging.getLogger(__name__)

# a deleted snapshot (app.core.retention's tombstone, state "deleted") the twin had not
# reached is skipped as well
_SETTLED_BAD = (SnapshotState.failed, SnapshotState.cancelled, "deleted")
_ENDED_BAD = (JobState.failed, JobState.cancelled)


@dataclass(frozen=True)
class Progress:
    """Where the twin stands: ``seq`` the newest snapshot it took into account (applied or
    skipped), ``snapshot_id`` the newest one whose changes it reflects, ``status``, and
    what it waits on: the next snapshot and, once there is one, its automatic comparison."""

    seq: int
    snapshot_id: str | None
    status: TwinStatus
    waiting_for: str | None = None
    comparison_id: str | None = None


def advance(session: Session, environment_id: str) -> Progress:
    """Bring the twin forward through every snapshot that is due, in seq order (see the
    module docstring); returns where it stopped. Never commits."""
    env = session.scalar(
        select(Environment)
        .where(Environment.id == environment_id)
        .with_for_update(key_share=True)  # FOR NO KEY UPDATE: rows that refer to it go on
        .execution_options(populate_existing=True)
    )
    if env is None:
        raise NotFound(f"environment {environment_id} not found")
    while True:
        head = _next_snapshot(session, env)
        if head is None:
            env.twin_blocked_by = None
            return _progress(env, TwinStatus.current)
        state, job = _snapshot_state(session, head)
        if state in _SETTLED_BAD:
            _skip(session, env, head, state, job)
            continue
        if state != SnapshotState.reconstructed:
            env.twin_blocked_by = None
            return _progress(env, TwinStatus.reconstructing, head)
        if env.twin_snapshot_id is None:
            _baseline(session, env, head)
            continue
        comparison = _automatic_comparison(session, head, env.twin_snapshot_id)
        if comparison is None:
            before = session.get(Snapshot, env.twin_snapshot_id)
            if before is None or before.state != SnapshotState.reconstructed:
                # the snapshot the twin reflects was deleted: compare with the newest
                # earlier one that is still there
                env.twin_snapshot_id = _newest_reconstructed_before(session, head)
                if env.twin_snapshot_id is None:
                    _baseline(session, env, head)
                    continue
                before = session.get(Snapshot, env.twin_snapshot_id)
            assert before is not None
            comparison = comparisons.create(
                session,
                env.id,
                before,
                head,
                dict(env.options.get("compare", {})),
                automatic=True,
            )
            env.twin_blocked_by = None
            return _progress(env, TwinStatus.comparing, head, comparison)
        ended = _comparison_state(session, comparison)
        if ended == ComparisonState.succeeded:
            _apply(session, env, head, comparison)
            continue
        if ended in (ComparisonState.failed, ComparisonState.cancelled):
            if env.twin_blocked_by != comparison.id:
                env.twin_blocked_by = comparison.id
                _announce_blocked(session, env, head, comparison)
            return _progress(env, TwinStatus.blocked, head, comparison)
        env.twin_blocked_by = None
        return _progress(env, TwinStatus.comparing, head, comparison)


def progress(session: Session, env: Environment) -> Progress:
    """Where the twin of ``env`` stands, read only (the same walk as :func:`advance`, up
    to its first step)."""
    head = _next_snapshot(session, env, refresh=False)
    if head is None:
        return _progress(env, TwinStatus.current)
    state, _job = _snapshot_state(session, head, refresh=False)
    if state != SnapshotState.reconstructed or env.twin_snapshot_id is None:
        return _progress(env, TwinStatus.reconstructing, head)
    comparison = _automatic_comparison(session, head, env.twin_snapshot_id, refresh=False)
    if comparison is None:
        return _progress(env, TwinStatus.comparing, head)
    ended = _comparison_state(session, comparison, refresh=False)
    if ended in (ComparisonState.failed, ComparisonState.cancelled):
        return _progress(env, TwinStatus.blocked, head, comparison)
    return _progress(env, TwinStatus.comparing, head, comparison)


def _progress(
    env: Environment,
    status: TwinStatus,
    head: Snapshot | None = None,
    comparison: Comparison | None = None,
) -> Progress:
    return Progress(
        seq=env.twin_seq or 0,
        snapshot_id=env.twin_snapshot_id,
        status=status,
        waiting_for=head.id if head is not None else None,
        comparison_id=comparison.id if comparison is not None else None,
    )


def _fresh(refresh: bool) -> dict[str, Any]:
    # the chain decides on rows other transactions commit: read them, not the session's
    # copies (own changes are flushed first, so they are read back too)
    return {"populate_existing": True} if refresh else {}


def _next_snapshot(session: Session, env: Environment, refresh: bool = True) -> Snapshot | None:
    return session.scalar(
        select(Snapshot)
        .where(Snapshot.environment_id == env.id, Snapshot.seq > (env.twin_seq or 0))
        .order_by(Snapshot.seq)
        .limit(1)
        .execution_options(**_fresh(refresh))
    )


def _snapshot_state(
    session: Session, snap: Snapshot, refresh: bool = True
) -> tuple[SnapshotState | str, Job | None]:
    """The snapshot's state, or failed/cancelled when its job ended so and the snapshot row
    was not brought along (the job row is the truth)."""
    job = session.scalar(
        select(Job)
        .where(Job.snapshot_id == snap.id, Job.kind == JobKind.snapshot)
        .order_by(Job.created_at.desc())
        .limit(1)
        .execution_options(**_fresh(refresh))
    )
    state = snap.state
    unfinished = state in (SnapshotState.uploaded, SnapshotState.processing)
    if unfinished and job is not None and job.state in _ENDED_BAD:
        cancelled = job.state == JobState.cancelled
        state = SnapshotState.cancelled if cancelled else SnapshotState.failed
    return state, job


def _automatic_comparison(
    session: Session, after: Snapshot, before_id: str, refresh: bool = True
) -> Comparison | None:
    return session.scalar(
        select(Comparison)
        .where(
            Comparison.after_id == after.id,
            Comparison.before_id == before_id,
            Comparison.automatic.is_(True),
        )
        .order_by(Comparison.created_at.desc())
        .limit(1)
        .execution_options(**_fresh(refresh))
    )


def _comparison_state(
    session: Session, comparison: Comparison, refresh: bool = True
) -> ComparisonState | str:
    """The comparison's state, or failed/cancelled when its job ended so unfinished."""
    if comparison.state in (ComparisonState.queued, ComparisonState.running):
        job = session.scalar(
            select(Job).where(Job.id == comparison.job_id).execution_options(**_fresh(refresh))
        )
        if job is not None and job.state in _ENDED_BAD:
            return (
                ComparisonState.cancelled
                if job.state == JobState.cancelled
                else ComparisonState.failed
            )
    return comparison.state


def _newest_reconstructed_before(session: Session, snap: Snapshot) -> str | None:
    return session.scalar(
        select(Snapshot.id)
        .where(
            Snapshot.environment_id == snap.environment_id,
            Snapshot.seq < snap.seq,
            Snapshot.state == SnapshotState.reconstructed,
        )
        .order_by(Snapshot.seq.desc())
        .limit(1)
    )


def _baseline(session: Session, env: Environment, head: Snapshot) -> None:
    """The first snapshot the twin reflects: its inventory fills the twin
    (:func:`app.core.inventory.fill_baseline`)."""
    inventory.fill_baseline(session, env, head)
    _settle(session, env, head, TwinUpdate.baseline, None)


def _skip(
    session: Session,
    env: Environment,
    head: Snapshot,
    state: SnapshotState | str,
    job: Job | None,
) -> None:
    reason: dict[str, Any] = {"state": str(state)}
    if job is not None:
        reason.update(code=job.error_code, detail=job.error_detail)
    _settle(session, env, head, TwinUpdate.skipped, None, reason=reason)


def _settle(
    session: Session,
    env: Environment,
    head: Snapshot,
    outcome: TwinUpdate,
    comparison: Comparison | None,
    reason: dict[str, Any] | None = None,
) -> None:
    """Record that the twin took ``head`` into account, and the ``twin.updated`` event."""
    head.twin_update = outcome
    env.twin_seq = head.seq
    if outcome != TwinUpdate.skipped:
        env.twin_snapshot_id = head.id
    env.twin_blocked_by = None
    session.flush()
    data: dict[str, Any] = {
        "environment": env.id,
        "snapshot": head.id,
        "seq": head.seq,
        "outcome": str(outcome),
        "comparison": comparison.id if comparison is not None else None,
        "links": {
            "state": f"/v1/environments/{env.id}/state",
            "snapshot": f"/v1/snapshots/{head.id}",
        },
    }
    if reason is not None:
        data["reason"] = reason
    if outcome == TwinUpdate.baseline:
        data["instances"] = [
            {
                "instance_id": instance.id,
                "external_id": instance.external_id,
                "change_type": record.change_type,
                "present": True,
            }
            for record, instance in inventoried_instances(session, head.id)
        ]
    if comparison is not None:
        data["links"]["comparison"] = f"/v1/comparisons/{comparison.id}"
        data["instances"] = [
            {
                "instance_id": instance.id,
                "external_id": instance.external_id,
                "change_type": record.change_type,
                "present": instance.closed_snapshot_id != head.id,
            }
            for record, instance in changed_instances(session, head.id, comparison.id)
        ]
    events.record(
        session,
        EventType.twin_updated,
        environment_id=env.id,
        subject=f"environments/{env.id}/state",
        data=data,
    )


def _apply(session: Session, env: Environment, head: Snapshot, comparison: Comparison) -> None:
    changes = [
        {
            "type": change.type,
            "object": change.object_name,
            "instance_id": change.instance_id,
            "pose": change.pose,
            "pose_quality": change.pose_quality,
            "centroid_env": change.centroid_env,
            "replaced_instance_id": change.replaced_instance_id,
        }
        for change in comparison.changes
    ]
    object_ids = {
        change.object_name: change.object_id
        for change in comparison.changes
        if change.object_name and change.object_id
    }
    apply_changes(session, env.id, head.id, comparison.id, changes, object_ids)
    inventory.confirm(session, env, head, comparison.id)
    comparison.applied_to_state = True
    comparison.applied_at = utcnow()
    _settle(session, env, head, TwinUpdate.applied, comparison)


def _announce_blocked(
    session: Session, env: Environment, head: Snapshot, comparison: Comparison
) -> None:
    job = session.get(Job, comparison.job_id)
    events.record(
        session,
        EventType.twin_blocked,
        environment_id=env.id,
        subject=f"environments/{env.id}/state",
        data={
            "environment": env.id,
            "snapshot": head.id,
            "seq": head.seq,
            "comparison": comparison.id,
            "twin_seq": env.twin_seq or 0,
            "error": {
                "code": job.error_code if job else None,
                "detail": job.error_detail if job else None,
            },
            "links": {
                "comparison": f"/v1/comparisons/{comparison.id}",
                "retry": f"/v1/comparisons/{comparison.id}/retry",
            },
        },
    )


def current(session: Session, environment_id: str) -> list[TwinInstance]:
    """Open instances (not removed), oldest first."""
    return open_instances(session, environment_id)


def history(
    session: Session, environment_id: str, instance_id: str
) -> tuple[TwinInstance, list[InstancePose]]:
    instance = session.get(TwinInstance, instance_id)
    if instance is None or instance.environment_id != environment_id:
        raise NotFound(f"instance {instance_id} not found in environment {environment_id}")
    poses = session.scalars(
        select(InstancePose)
        .where(InstancePose.instance_id == instance_id)
        .order_by(InstancePose.created_at)
    ).all()
    return instance, list(poses)


def state_at(
    session: Session, environment_id: str, seq: int
) -> list[tuple[TwinInstance, InstancePose]]:
    """The twin as it stood once snapshot number ``seq`` was applied: every instance open at
    that time with its latest history record then (pose None when never estimated). A
    record or instance that belongs to no snapshot (seeded before the twin reflected any,
    :mod:`app.core.seeding`) counts as seq 0: it stands from the start."""
    created = aliased(Snapshot)
    closed = aliased(Snapshot)
    instances = session.scalars(
        select(TwinInstance)
        .outerjoin(created, TwinInstance.created_snapshot_id == created.id)
        .outerjoin(closed, TwinInstance.closed_snapshot_id == closed.id)
        .where(
            TwinInstance.environment_id == environment_id,
            or_(TwinInstance.created_snapshot_id.is_(None), created.seq <= seq),
            or_(closed.id.is_(None), closed.seq > seq),
        )
        .order_by(TwinInstance.created_at)
    ).all()
    out: list[tuple[TwinInstance, InstancePose]] = []
    for instance in instances:
        record = session.scalar(
            select(InstancePose)
            .outerjoin(Snapshot, InstancePose.snapshot_id == Snapshot.id)
            .where(
                InstancePose.instance_id == instance.id,
                or_(InstancePose.snapshot_id.is_(None), Snapshot.seq <= seq),
            )
            .order_by(func.coalesce(Snapshot.seq, 0).desc(), InstancePose.created_at.desc())
            .limit(1)
        )
        if record is not None:
            out.append((instance, record))
    return out


def apply_changes(
    session: Session,
    environment_id: str,
    snapshot_id: str,
    comparison_id: str,
    changes: list[dict[str, Any]],
    object_ids: dict[str, str],
) -> None:
    """Write a comparison's changes into the twin: added creates an instance, removed closes
    it, moved appends a pose, swapped closes one and creates another; unidentified changes
    leave the twin alone. Every pose goes into the instance's history."""
    now = utcnow()

    def record(instance_id: str, change_type: str, change: dict[str, Any] | None) -> None:
        session.add(
            InstancePose(
                instance_id=instance_id,
                snapshot_id=snapshot_id,
                comparison_id=comparison_id,
                change_type=change_type,
                pose=change.get("pose") if change else None,
                centroid_env=change.get("centroid_env") if change else None,
            )
        )

    def close(instance_id: str | None, change_type: str) -> None:
        instance = session.get(TwinInstance, instance_id) if instance_id else None
        if instance is None or instance.closed_snapshot_id is not None:
            log.warning("change %s names no open instance %s", change_type, instance_id)
            return
        instance.closed_snapshot_id, instance.closed_at = snapshot_id, now
        record(instance.id, change_type, None)

    def create(change: dict[str, Any]) -> None:
        name = str(change["object"])
        session.add(
            TwinInstance(
                id=change["instance_id"],
                environment_id=environment_id,
                object_name=name,
                object_id=object_ids.get(name),
                pose=change.get("pose"),
                pose_quality=change.get("pose_quality"),
                centroid_env=change.get("centroid_env"),
                since_snapshot_id=snapshot_id,
                created_snapshot_id=snapshot_id,
            )
        )
        session.flush()
        record(change["instance_id"], str(change["type"]), change)

    for change in changes:
        kind = change["type"]
        if kind == ChangeType.added:
            create(change)
        elif kind == ChangeType.removed:
            close(change.get("instance_id"), ChangeType.removed)
        elif kind == ChangeType.moved:
            instance = session.get(TwinInstance, change.get("instance_id") or "")
            if instance is None:
                create({**change, "type": ChangeType.added})
                continue
            if instance.closed_snapshot_id is not None:
                # closed meanwhile (retired by hand while this comparison ran): the object
                # is there, as a new instance (the closed one keeps its id and history)
                log.warning("moved names closed instance %s: added anew", instance.id)
                create({**change, "type": ChangeType.added, "instance_id": new_id()})
                continue
            instance.pose, instance.pose_quality = change.get("pose"), change.get("pose_quality")
            instance.centroid_env = change.get("centroid_env")
            instance.since_snapshot_id = snapshot_id
            record(instance.id, ChangeType.moved, change)
        elif kind == ChangeType.swapped:
            close(change.get("replaced_instance_id"), ChangeType.swapped)
            create(change)
    session.flush()
