"""The job state machine. The job row is the single truth for state, stage, progress,
error, heartbeat and cancel intent; the Celery message only says "look at job X".

    queued ──claim──▶ running ──finish──▶ succeeded | failed | cancelled
      │                  │ heartbeat stops: back to queued (attempts left) or failed
      └──cancel──▶ cancelled        cancel ──▶ cancel_requested, the worker stops at the next
                                               progress report
    running ──requeue──▶ queued   (the worker hit a transient database error)

A job that ends failed or cancelled takes its subject with it (:mod:`app.core.lifecycle`).

``attempts`` is a fencing token: every write of a running job names the attempt that
claimed it, so a zombie worker whose job was taken over can never overwrite the result.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from datetime import UTC, datetime, timedelta
from typing import Any

from sqlalchemy import select, update
from sqlalchemy.orm import Session

from app.core import lifecycle, queue
from app.core.enums import JobKind, JobState
from app.core.errors import Conflict, NotFound
from app.core.models import Job, utcnow
from app.core.settings import Settings

log = logging.getLogger(__name__)


def create(
    session: Session,
    kind: JobKind,
    task_name: str,
    *,
    preset: str = "default",
    options: dict[str, Any] | None = None,
    **subject: str | None,
) -> Job:
    """Insert a queued job and enqueue its task after commit."""
    job = Job(
        kind=kind,
        task_name=task_name,
        preset=preset,
        options=options or {},
        state=JobState.queued,
        enqueued_at=utcnow(),
        sends=1,
        **subject,
    )
    session.add(job)
    session.flush()
    queue.enqueue(session, task_name, job_id=job.id)
    return job


def attempt_folder(root: str, job_id: str, attempt: int) -> str:
    """The folder below ``root`` where attempt ``attempt`` of job ``job_id`` publishes its
    files (workers.runner.publish), so attempts never write to each other's keys."""
    return f"{root}/{job_id}-{attempt}"


def get(session: Session, job_id: str) -> Job:
    job = session.get(Job, job_id)
    if job is None:
        raise NotFound(f"job {job_id} not found")
    return job


def claim(session: Session, job_id: str, worker: str) -> int | None:
    """Atomically move a queued job to running; returns the attempt number (the fencing
    token) or None when another worker has it or it is already final."""
    now = utcnow()
    result = session.execute(
        update(Job)
        .where(Job.id == job_id, Job.state == JobState.queued, Job.cancel_requested.is_(False))
        .values(
            state=JobState.running,
            started_at=now,
            heartbeat_at=now,
            attempts=Job.attempts + 1,
            worker=worker,
            stage="starting",
        )
    )
    if result.rowcount != 1:  # type: ignore[attr-defined]
        return None
    attempt: int = session.scalar(select(Job.attempts).where(Job.id == job_id)) or 0
    return attempt


def _owned(job_id: str, attempt: int) -> Any:
    return (Job.id == job_id, Job.state == JobState.running, Job.attempts == attempt)


def report(
    session: Session, job_id: str, attempt: int, stage: str | None, progress: float | None
) -> bool:
    """Write stage/progress/heartbeat for a running attempt; returns True when the user asked
    to cancel (or the attempt lost the job), so the worker should stop."""
    values: dict[str, Any] = {"heartbeat_at": utcnow()}
    if stage is not None:
        values["stage"] = stage
    if progress is not None:
        values["progress"] = min(max(float(progress), 0.0), 1.0)
    result = session.execute(update(Job).where(*_owned(job_id, attempt)).values(**values))
    if result.rowcount != 1:  # type: ignore[attr-defined]
        return True
    return bool(session.scalar(select(Job.cancel_requested).where(Job.id == job_id)))


def finish(
    session: Session,
    job_id: str,
    attempt: int,
    state: JobState,
    *,
    error_code: str | None = None,
    error_detail: str | None = None,
    result: dict[str, Any] | None = None,
) -> Job | None:
    """End a running attempt; returns the job, or None when this attempt no longer owns it
    (the caller must then discard its results)."""
    if not state.is_final:
        raise ValueError(f"{state} is not a final state")
    values: dict[str, Any] = {
        "state": state,
        "finished_at": utcnow(),
        "error_code": error_code,
        "error_detail": error_detail,
    }
    if state == JobState.succeeded:
        values.update(progress=1.0, stage="done")
    if result is not None:
        values["result"] = result
    updated = session.execute(update(Job).where(*_owned(job_id, attempt)).values(**values))
    if updated.rowcount != 1:  # type: ignore[attr-defined]
        return None
    job = session.get(Job, job_id)
    if job is not None:
        session.refresh(job)
    return job


def requeue(session: Session, job_id: str, attempt: int) -> bool:
    """Give a running attempt's job back to the queue and send it again after commit (the
    worker could not finish it for a reason that is not the job's: a transient database
    error); False when this attempt no longer owns it."""
    now = utcnow()
    updated = session.execute(
        update(Job)
        .where(*_owned(job_id, attempt))
        .values(
            state=JobState.queued,
            stage="requeued",
            worker=None,
            enqueued_at=now,
            sends=Job.sends + 1,
        )
    )
    if updated.rowcount != 1:  # type: ignore[attr-defined]
        return False
    task_name = session.scalar(select(Job.task_name).where(Job.id == job_id))
    queue.enqueue(session, str(task_name), job_id=job_id)
    return True


def fail_unclaimed(session: Session, job_id: str, code: str, detail: str) -> Job | None:
    """Fail a job that no worker could even start (its task crashed before claiming it);
    returns it, or None when it was not queued."""
    updated = session.execute(
        update(Job)
        .where(Job.id == job_id, Job.state == JobState.queued)
        .values(state=JobState.failed, finished_at=utcnow(), error_code=code, error_detail=detail)
    )
    if updated.rowcount != 1:  # type: ignore[attr-defined]
        return None
    job = get(session, job_id)
    session.refresh(job)
    return job


def cancel(session: Session, job_id: str) -> Job:
    """Cancel now when queued (its subject is cancelled too, with a ``job.cancelled``
    event); ask the worker to stop when running; 409 when already final."""
    job = session.get(Job, job_id, with_for_update=True)
    if job is None:
        raise NotFound(f"job {job_id} not found")
    if JobState(job.state).is_final:
        raise Conflict(f"job {job_id} is already {job.state}", code="JobFinished")
    job.cancel_requested = True
    if job.state == JobState.queued:
        job.state = JobState.cancelled
        job.finished_at = utcnow()
        job.error_code, job.error_detail = "Cancelled", "cancelled while queued"
        session.flush()
        lifecycle.settle(session, job)
    session.flush()
    return job


def sweep(session: Session, settings: Settings, now: datetime | None = None) -> dict[str, int]:
    """Repair what crashed processes and lost broker messages leave behind.

    - queued jobs whose message may be lost (last sent long ago) are sent again, with the
      wait doubling at each send (duplicates are harmless: claim is conditional);
    - running jobs whose heartbeat stopped go back to the queue while attempts remain,
      otherwise they fail with ``WorkerLost``; those whose cancel was asked end cancelled.
      A job that ends takes its subject with it (:func:`app.core.lifecycle.settle`).

    Each job is handled in its own savepoint: one that cannot be handled is logged, left as
    it was (the next sweep tries again) and counted in ``errors``; the others go on.
    Returns counts for logging.
    """
    now = now or utcnow()
    counts = {"resent": 0, "requeued": 0, "failed": 0, "cancelled": 0, "errors": 0}
    queued = session.scalars(
        select(Job).where(Job.state == JobState.queued).with_for_update(skip_locked=True)
    ).all()
    for job in queued:
        wait = min(settings.requeue_after_s * 2 ** max(job.sends - 1, 0), 3600.0)
        last = _aware(job.enqueued_at or job.created_at)
        if now - last >= timedelta(seconds=wait):
            _each(session, job, counts, lambda job: _resend(session, job, now))
    stale_before = now - timedelta(seconds=settings.heartbeat_timeout_s)
    running = session.scalars(
        select(Job).where(Job.state == JobState.running).with_for_update(skip_locked=True)
    ).all()
    for job in running:
        heartbeat = _aware(job.heartbeat_at or job.started_at or job.created_at)
        if heartbeat < stale_before:
            _each(session, job, counts, lambda job: _recover(session, job, settings, now))
    session.flush()
    return counts


def _each(session: Session, job: Job, counts: dict[str, int], handle: Callable[[Job], str]) -> None:
    """Run ``handle(job)`` in a savepoint; count its outcome, or log its error and go on."""
    job_id = job.id
    try:
        with session.begin_nested():
            outcome: str = handle(job)
    except Exception as exc:
        if lifecycle.connection_lost(exc):  # the whole transaction is gone: nothing to go on
            raise
        log.exception("sweep: job %s could not be handled; left as it was", job_id)
        counts["errors"] += 1
        return
    counts[outcome] += 1
    if outcome in ("resent", "requeued"):  # sent only once its savepoint stands
        queue.enqueue(session, job.task_name, job_id=job.id)


def _resend(session: Session, job: Job, now: datetime) -> str:
    job.enqueued_at, job.sends = now, job.sends + 1
    session.flush()
    return "resent"


def _recover(session: Session, job: Job, settings: Settings, now: datetime) -> str:
    """A running job whose worker stopped beating: cancel, requeue or fail it."""
    if job.cancel_requested:
        job.state, job.finished_at = JobState.cancelled, now
        job.error_code, job.error_detail = "Cancelled", "worker stopped after cancel"
        outcome = "cancelled"
    elif job.attempts < settings.max_job_attempts:
        job.state, job.stage, job.worker = JobState.queued, "requeued", None
        job.enqueued_at, job.sends = now, job.sends + 1
        session.flush()
        return "requeued"
    else:
        job.state, job.finished_at = JobState.failed, now
        job.error_code = "WorkerLost"
        job.error_detail = (
            f"no heartbeat for {settings.heartbeat_timeout_s:.0f} s after "
            f"{job.attempts} attempts; the worker died or hung"
        )
        outcome = "failed"
    session.flush()
    lifecycle.settle(session, job)
    return outcome


def _aware(value: datetime) -> datetime:
    """SQLite returns naive datetimes; they are UTC."""
    return value if value.tzinfo else value.replace(tzinfo=UTC)
