"""Comparisons of two snapshots of one environment: created automatically after a
reconstruction, or on request with other options."""

from __future__ import annotations

from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.core import jobs
from app.core.enums import ComparisonState, JobKind, JobState, SnapshotState
from app.core.errors import Conflict, InvalidInput, NotFound
from app.core.models import Comparison, Environment, Job, Snapshot, new_id
from app.core.options import check_stage_options

TASK = "comparison.run"


def create(
    session: Session,
    environment_id: str,
    before: Snapshot,
    after: Snapshot,
    options: dict[str, Any] | None,
    *,
    automatic: bool = False,
) -> Comparison:
    """A queued comparison and its job; 422/409 when the snapshots cannot be compared, 422
    for options the compare stage would refuse (requested comparisons; an automatic one
    takes the environment's, checked when it was created)."""
    if not automatic:
        options = check_stage_options("compare", options)
    for role, snap in (("before", before), ("after", after)):
        if snap.environment_id != environment_id:
            raise InvalidInput(f"{role}: snapshot {snap.id} belongs to another environment")
        if snap.state != SnapshotState.reconstructed:
            raise Conflict(
                f"{role}: snapshot {snap.id} is {snap.state}, not reconstructed",
                code="SnapshotNotReconstructed",
            )
    if before.id == after.id:
        raise InvalidInput("before and after are the same snapshot")
    options = dict(options or {})
    preset = str(options.pop("preset", "default"))
    comparison_id = new_id()
    job = jobs.create(
        session,
        JobKind.comparison,
        TASK,
        preset=preset,
        options=options,
        environment_id=environment_id,
        comparison_id=comparison_id,
    )
    comparison = Comparison(
        id=comparison_id,
        environment_id=environment_id,
        before_id=before.id,
        after_id=after.id,
        automatic=automatic,
        options={"preset": preset, **options},
        job_id=job.id,
    )
    session.add(comparison)
    session.flush()
    return comparison


def retry(session: Session, comparison_id: str) -> Comparison:
    """Run a failed or cancelled comparison again: a new queued job, same snapshots and
    options, results cleared. 404 when unknown; 409 ComparisonNotRetryable unless it failed
    or was cancelled, SnapshotNotReconstructed when a snapshot is gone. An automatic
    comparison that held its environment's twin (see app.core.twin) lets the chain go on
    once it succeeds."""
    comparison = session.scalar(
        select(Comparison)
        .where(Comparison.id == comparison_id)
        .with_for_update()
        .execution_options(populate_existing=True)
    )
    if comparison is None:
        raise NotFound(f"comparison {comparison_id} not found")
    job = session.get(Job, comparison.job_id)
    ended = comparison.state in (ComparisonState.failed, ComparisonState.cancelled) or (
        comparison.state != ComparisonState.succeeded
        and job is not None
        and job.state in (JobState.failed, JobState.cancelled)
    )
    if not ended:
        raise Conflict(
            f"comparison {comparison_id} is {comparison.state}; only a failed or cancelled "
            "comparison can be retried",
            code="ComparisonNotRetryable",
        )
    for role, snapshot_id in (("before", comparison.before_id), ("after", comparison.after_id)):
        snap = session.get(Snapshot, snapshot_id)
        if snap is None or snap.state != SnapshotState.reconstructed:
            raise Conflict(
                f"{role}: snapshot {snapshot_id} is no longer reconstructed",
                code="SnapshotNotReconstructed",
            )
    options = {k: v for k, v in comparison.options.items() if k not in ("preset", "resolved")}
    retried = jobs.create(
        session,
        JobKind.comparison,
        TASK,
        preset=str(comparison.options.get("preset", "default")),
        options=options,
        environment_id=comparison.environment_id,
        comparison_id=comparison.id,
    )
    comparison.job_id = retried.id
    comparison.state = ComparisonState.queued
    comparison.completed_at = None
    comparison.distances, comparison.clusters = {}, []
    comparison.changes.clear()
    env = session.scalar(
        select(Environment)
        .where(Environment.id == comparison.environment_id)
        .with_for_update(key_share=True)
    )
    if env is not None and env.twin_blocked_by == comparison.id:
        env.twin_blocked_by = None  # a new failure is announced again
    session.flush()
    return comparison


def get(session: Session, comparison_id: str) -> Comparison:
    comparison = session.get(Comparison, comparison_id)
    if comparison is None:
        raise NotFound(f"comparison {comparison_id} not found")
    return comparison


def list_for(session: Session, environment_id: str) -> list[Comparison]:
    """Every comparison of an environment, newest first."""
    return list(
        session.scalars(
            select(Comparison)
            .where(Comparison.environment_id == environment_id)
            .order_by(Comparison.created_at.desc())
        ).all()
    )
