"""What a job's bad end means for its subject.

A job works on one subject: a snapshot (``snapshot.process``), a comparison
(``comparison.run``) or a library object (``object.prepare``). When the job ends ``failed``
or ``cancelled`` — whoever ends it: the cancel route, the worker's runner, the sweeper, a task
that could not even start — :func:`settle` brings the subject to the same end and records the
job's event (``job.failed`` or ``job.cancelled``), in the caller's transaction:

    snapshot    uploaded | processing  ──▶ failed | cancelled   (quality.error says why)
    comparison  queued | running       ──▶ failed | cancelled
    object      processing             ──▶ failed | cancelled

A subject that already reached an end of its own (a reconstructed snapshot, a ready object)
is never rewritten, and a subject deleted meanwhile is skipped: a failure handler must never
fail, or the job would stay ``running`` and the sweeper would trip over it at every pass.
"""

from __future__ import annotations

import logging
from typing import Any

from sqlalchemy.exc import DBAPIError, OperationalError
from sqlalchemy.orm import Session

from app.core import events, twin
from app.core.enums import (
    ComparisonState,
    EventType,
    JobKind,
    JobState,
    ObjectState,
    SnapshotState,
)
from app.core.models import Comparison, Job, LibraryObject, Snapshot

log = logging.getLogger(__name__)

ENDS = {JobState.failed: EventType.job_failed, JobState.cancelled: EventType.job_cancelled}


def settle(session: Session, job: Job) -> None:
    """End ``job``'s subject the way the job ended (``failed`` or ``cancelled``) and record
    the job's event. Never commits.

    The subject is updated inside a savepoint: should that fail for any reason other than a
    lost database connection, the error is logged and the job still ends with its event.
    """
    state = JobState(job.state)
    if state not in ENDS:
        raise ValueError(f"job {job.id} is {state}; only failed or cancelled jobs are settled")
    try:
        with session.begin_nested():
            _end_subject(session, job, state)
    except Exception as exc:
        if connection_lost(exc):
            raise
        log.exception("job %s: could not end its %s; the job ends anyway", job.id, job.kind)
    events.record(
        session,
        ENDS[state],
        environment_id=job.environment_id,
        subject=f"jobs/{job.id}",
        data=_event_data(job),
    )
    if job.environment_id is not None and job.kind in (JobKind.snapshot, JobKind.comparison):
        # the twin's chain (app.core.twin): a failed snapshot is skipped and the next one
        # compared; a failed automatic comparison holds the twin, announced as twin.blocked
        try:
            with session.begin_nested():
                twin.advance(session, job.environment_id)
        except Exception as exc:
            if connection_lost(exc):
                raise
            log.exception("job %s: could not move the twin of %s on", job.id, job.environment_id)


def _end_subject(session: Session, job: Job, state: JobState) -> None:
    cancelled = state == JobState.cancelled
    if job.snapshot_id is not None:
        snap = session.get(Snapshot, job.snapshot_id)
        if snap is not None and snap.state in (SnapshotState.uploaded, SnapshotState.processing):
            snap.state = SnapshotState.cancelled if cancelled else SnapshotState.failed
            error = {"code": job.error_code, "detail": job.error_detail}
            snap.quality = {**(snap.quality or {}), "error": error}
    if job.comparison_id is not None:
        comparison = session.get(Comparison, job.comparison_id)
        if comparison is not None and comparison.state in (
            ComparisonState.queued,
            ComparisonState.running,
        ):
            comparison.state = ComparisonState.cancelled if cancelled else ComparisonState.failed
    if job.object_id is not None:
        # a soft-deleted object still gets its end: its row stays for the history
        obj = session.get(LibraryObject, job.object_id)
        if obj is not None and obj.state == ObjectState.processing:
            obj.state = ObjectState.cancelled if cancelled else ObjectState.failed
    session.flush()


def _event_data(job: Job) -> dict[str, Any]:
    return {
        "job": job.id,
        "kind": str(job.kind),
        "state": str(job.state),
        "error": {"code": job.error_code, "detail": job.error_detail},
        "snapshot": job.snapshot_id,
        "comparison": job.comparison_id,
        "object": job.object_id,
    }


def connection_lost(exc: BaseException) -> bool:
    """The database went away: the whole transaction is lost, a savepoint cannot save it."""
    return isinstance(exc, OperationalError) or (
        isinstance(exc, DBAPIError) and exc.connection_invalidated
    )
