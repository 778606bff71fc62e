"""The job state machine. The job row is the single truth for state, stage, progress,
error, heartbeat and cancel intent; the Celery message only says "look at job X".

    queued ──claim──▶ running ──finish──▶ succeeded | failed | cancelled
      │                  │ heartbeat stops: back to queued (attempts left) or failed
      └──cancel──▶ cancelled        cancel ──▶ cancel_requested, the worker stops at the next
                                               progress report

``attempts`` is a fencing token: every write of a running job names the attempt that
claimed it, so a zombie worker whose job was taken over can never overwrite the result.
"""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from typing import Any

from sqlalchemy import select, update
from sqlalchemy.orm import Session

from app.core import events, queue
from app.core.enums import EventType, JobKind, JobState
from app.core.errors import Conflict, NotFound
from app.core.models import Job, utcnow
from app.core.settings import Settings


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


def record_failed(session: Session, job: Job) -> None:
    """The ``job.failed`` event, in the transaction that fails the job."""
    events.record(
        session,
        EventType.job_failed,
        environment_id=job.environment_id,
        subject=f"jobs/{job.id}",
        data={
            "job": job.id,
            "kind": str(job.kind),
            "error": {"code": job.error_code, "detail": job.error_detail},
            "snapshot": job.snapshot_id,
            "comparison": job.comparison_id,
            "object": job.object_id,
        },
    )


def cancel(session: Session, job_id: str) -> Job:
    """Cancel now when queued; ask the worker to stop when running; 409 when already final."""
    job = session.get(Job, job_id, with_for_update=True)
    if job is None:
        raise NotFound(f"job {job_id} not found")
    if JobState(job.state).is_final:
        raise Conflict(f"job {job_id} is already {job.state}", code="JobFinished")
    if job.state == JobState.queued:
        job.state = JobState.cancelled
        job.finished_at = utcnow()
        job.error_code, job.error_detail = "Cancelled", "cancelled while queued"
    job.cancel_requested = True
    session.flush()
    return job


def sweep(session: Session, settings: Settings, now: datetime | None = None) -> dict[str, int]:
    """Repair what crashed processes and lost broker messages leave behind.

    - queued jobs whose message may be lost (last sent long ago) are sent again, with the
      wait doubling at each send (duplicates are harmless: claim is conditional);
    - running jobs whose heartbeat stopped go back to the queue while attempts remain,
      otherwise they fail with ``WorkerLost``.
    Returns counts for logging. Jobs it fails are returned in ``session.info['failed_jobs']``
    so the caller can emit events in the same transaction.
    """
    now = now or utcnow()
    counts = {"resent": 0, "requeued": 0, "failed": 0}
    queued = session.scalars(
        select(Job).where(Job.state == JobState.queued).with_for_update(skip_locked=True)
    ).all()
    for job in queued:
        wait = min(settings.requeue_after_s * 2 ** max(job.sends - 1, 0), 3600.0)
        last = _aware(job.enqueued_at or job.created_at)
        if now - last >= timedelta(seconds=wait):
            job.enqueued_at, job.sends = now, job.sends + 1
            queue.enqueue(session, job.task_name, job_id=job.id)
            counts["resent"] += 1
    stale_before = now - timedelta(seconds=settings.heartbeat_timeout_s)
    running = session.scalars(
        select(Job).where(Job.state == JobState.running).with_for_update(skip_locked=True)
    ).all()
    failed: list[Job] = session.info.setdefault("failed_jobs", [])
    for job in running:
        heartbeat = _aware(job.heartbeat_at or job.started_at or job.created_at)
        if heartbeat >= stale_before:
            continue
        if job.cancel_requested:
            job.state, job.finished_at = JobState.cancelled, now
            job.error_code, job.error_detail = "Cancelled", "worker stopped after cancel"
        elif job.attempts < settings.max_job_attempts:
            job.state, job.stage, job.worker = JobState.queued, "requeued", None
            job.enqueued_at, job.sends = now, job.sends + 1
            queue.enqueue(session, job.task_name, job_id=job.id)
            counts["requeued"] += 1
        else:
            job.state, job.finished_at = JobState.failed, now
            job.error_code = "WorkerLost"
            job.error_detail = (
                f"no heartbeat for {settings.heartbeat_timeout_s:.0f} s after "
                f"{job.attempts} attempts; the worker died or hung"
            )
            failed.append(job)
            counts["failed"] += 1
    session.flush()
    return counts


def _aware(value: datetime) -> datetime:
    """SQLite returns naive datetimes; they are UTC."""
    return value if value.tzinfo else value.replace(tzinfo=UTC)
