"""The shape every job task has: claim → compute with no open session → persist.

``run_job(job_id, compute, persist)``:
1. claim the job in a short transaction (conditional UPDATE; nothing to do if another
   worker has it or it is already final, so a redelivered message is harmless);
2. call ``compute(ctx)`` holding no database session; it reports progress through
   ``ctx.progress`` (which also raises Cancelled when the user cancelled);
3. in one transaction, mark the job succeeded (only if this attempt still owns it: the
   attempt number is a fencing token) and ``persist`` the result, so results are written
   exactly once; on a failure mark the job failed (or cancelled) with a code, and its
   subject with it (:func:`app.core.lifecycle.settle`).

Transient database faults (a lock past the busy timeout, a PostgreSQL restart) are not the
job's failure. Progress writes skip them; the claim, the final write and the failure write
are retried for up to ``Settings.db_retry_s``; one met inside ``compute`` gives the job back
to the queue. A final write that cannot be retried safely (``persist`` had begun; the
commit may have happened) or a database down past the bound leaves the job ``running``
without a heartbeat, for the sweeper to requeue: never ``failed`` for a fault that was not
the job's.

Files a job makes are published before its persist transaction opens (:func:`publish`, in
``compute``), under a folder of this attempt (``<root>/<job id>-<attempt>``), so no bucket
transfer runs while the transaction holds row locks and a stale attempt (its job requeued
after a heartbeat timeout) never overwrites what the winner recorded. ``discard`` removes
them when the result is certainly not recorded; ``persist`` schedules the other attempts'
folders for deletion after its commit (:func:`app.core.retention.delete_after_commit`).
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import socket
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, TypeVar

from sqlalchemy.orm import Session

from app.core import jobs, lifecycle
from app.core.db import transaction
from app.core.enums import JobState
from app.core.errors import DomainError
from app.core.models import Job
from app.core.retention import delete_after_commit
from app.core.settings import Settings, get_settings
from app.core.storage import Storage, open_storage
from workers.pipeline.errors import Cancelled, PipelineError
from workers.progress import ProgressReporter
from workers.retry import FIRST_DELAY_S, MAX_DELAY_S, is_transient, retry_transient

log = logging.getLogger(__name__)
R = TypeVar("R")


@dataclass(frozen=True)
class JobContext:
    """What a compute step may use: a detached copy of the job row, its attempt number,
    the progress callback, a private work directory, storage and settings."""

    job: Job
    attempt: int
    progress: ProgressReporter
    work_dir: Path
    storage: Storage
    settings: Settings


class JobFailure(Exception):
    """Raised by glue code for an expected failure with a code a person can act on."""

    def __init__(self, code: str, detail: str) -> None:
        super().__init__(detail)
        self.code, self.detail = code, detail


def worker_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


@dataclass(frozen=True)
class Published:
    """Files an attempt published before persisting: ``folder`` is its own
    (``<root>/<job id>-<attempt>``); ``stale`` the other folders under ``root`` when it
    published (earlier attempts', killed or stale), to delete once its result is recorded."""

    folder: str
    stale: tuple[str, ...]

    def key(self, name: str) -> str:
        return f"{self.folder}/{name}"


def publish(ctx: JobContext, root: str, files: Mapping[str, Path] | Path) -> Published:
    """Move ``files`` in as this attempt's folder below ``root`` (a local folder: its
    contents; a mapping: name → local file or folder), then list ``root``'s other folders.
    Runs outside any transaction. When the store fails, what was moved in is removed and
    the OSError raised."""
    folder = jobs.attempt_folder(root, ctx.job.id, ctx.attempt)
    pairs = (
        [(files, folder)]
        if isinstance(files, Path)
        else [(path, f"{folder}/{name}") for name, path in files.items()]
    )
    try:
        for path, key in pairs:
            ctx.storage.move_in(path, key)
        others = sorted(f"{root}/{name}" for name in ctx.storage.folders(root))
    except BaseException:
        with contextlib.suppress(OSError):  # the store is failing; raise what failed first
            ctx.storage.delete_prefix(folder)
        raise
    return Published(folder, tuple(key for key in others if key != folder))


def drop_stale(session: Session, ctx: JobContext, published: Published) -> None:
    """Delete the folders other attempts left under ``published``'s root once ``session``
    commits (for ``persist``, which records ``published``)."""
    for key in published.stale:
        delete_after_commit(session, ctx.storage, key)


class HasPublished(Protocol):
    """A job result that carries what its attempt published."""

    @property
    def published(self) -> Published: ...


def unpublish(ctx: JobContext, result: HasPublished) -> None:
    """Remove the folder ``result``'s attempt published (a ``discard``: the result was not
    recorded)."""
    ctx.storage.delete_prefix(result.published.folder)


def run_job(
    job_id: str,
    compute: Callable[[JobContext], R],
    persist: Callable[[Session, JobContext, R], None],
    discard: Callable[[JobContext, R], None] | None = None,
) -> str:
    """Run one job to a final state; returns what happened (for logs and tests): succeeded,
    failed, cancelled, skipped (not ours to run), lost (another attempt owns it), requeued
    (a transient database error) or deferred (left running for the sweeper).

    ``discard(ctx, result)`` removes what ``compute`` published when the result is certainly
    not recorded: the attempt lost the job before persisting, ``persist`` raised (its
    transaction rolled back) or the user cancelled after ``compute``. After a transient
    error during ``persist`` or any error at the commit, the commit may have happened, so
    nothing is discarded; the next attempt's ``persist`` removes what is left."""
    settings = get_settings()
    bound = settings.db_retry_s
    attempt = retry_transient(lambda: _claim(job_id), bound_s=bound, what=f"claim of job {job_id}")
    if attempt is None:
        return "skipped"
    job = retry_transient(lambda: _read(job_id), bound_s=bound, what=f"read of job {job_id}")
    storage = open_storage(settings)
    work_dir = storage.scratch_path(f".work/{job_id}")
    work_dir.mkdir(parents=True, exist_ok=True)
    reporter = ProgressReporter(
        job_id, attempt, settings.progress_interval_s, settings.heartbeat_interval_s
    )
    ctx = JobContext(job, attempt, reporter, work_dir, storage, settings)
    computed: list[R] = []
    try:
        with reporter:
            computed.append(compute(ctx))
            reporter.check_cancelled()
        outcome = _succeed(ctx, persist, computed[0], discard)
    except Cancelled:
        if computed:
            _discard(ctx, discard, computed[0])
        outcome = _end(ctx, JobState.cancelled, "Cancelled", "cancelled by request")
    except (PipelineError, JobFailure, DomainError) as exc:
        outcome = _end(ctx, JobState.failed, exc.code, exc.detail)
    except Exception as exc:
        if is_transient(exc):
            log.warning("job %s met a transient database error: %s", job_id, exc)
            outcome = _requeue(ctx, f"{type(exc).__name__}: {exc}")
        else:
            log.exception("job %s failed unexpectedly", job_id)
            outcome = _end(ctx, JobState.failed, "InternalError", f"{type(exc).__name__}: {exc}")
    if outcome != "lost":
        shutil.rmtree(work_dir, ignore_errors=True)
    return outcome


def _claim(job_id: str) -> int | None:
    with transaction() as session:
        return jobs.claim(session, job_id, worker_name())


def _read(job_id: str) -> Job:
    with transaction() as session:
        return jobs.get(session, job_id)


def _succeed(
    ctx: JobContext,
    persist: Callable[[Session, JobContext, R], None],
    result: R,
    discard: Callable[[JobContext, R], None] | None,
) -> str:
    """Mark the job succeeded and persist its result in one transaction. A transient error
    before ``persist`` began is retried (nothing outside the database was touched yet); one
    after it gives the job back to the queue, since the commit may have happened.
    ``discard`` runs when the result is certainly not recorded (see :func:`run_job`)."""
    job_id, attempt = ctx.job.id, ctx.attempt
    deadline = time.monotonic() + ctx.settings.db_retry_s
    delay = FIRST_DELAY_S
    while True:
        began = committing = False
        try:
            with transaction() as session:
                owned = jobs.finish(session, job_id, attempt, JobState.succeeded) is not None
                if owned:
                    began = True
                    persist(session, ctx, result)
                committing = True  # an error from here on may follow the commit
            if not owned:
                log.warning("job %s attempt %s lost ownership; result discarded", job_id, attempt)
                _discard(ctx, discard, result)
                return "lost"
            return "succeeded"
        except Exception as exc:
            if not is_transient(exc):
                if not committing:  # rolled back
                    _discard(ctx, discard, result)
                raise
            if began:
                log.warning("job %s: the database failed during persist: %s", job_id, exc)
                return _requeue(ctx, f"{type(exc).__name__}: {exc}")
            if time.monotonic() + delay > deadline:
                log.error("job %s: database unavailable; left for the sweeper: %s", job_id, exc)
                return "deferred"
            log.warning("job %s: final write failed, retrying in %.1f s: %s", job_id, delay, exc)
        time.sleep(delay)
        delay = min(delay * 2, MAX_DELAY_S)


def _discard(ctx: JobContext, discard: Callable[[JobContext, R], None] | None, result: R) -> None:
    """``discard(ctx, result)``; a failure is logged (the next attempt's persist or the
    snapshot's deletion removes what is left), never the job's."""
    if discard is None:
        return
    try:
        discard(ctx, result)
    except Exception:
        log.exception("job %s: could not remove what attempt %s published", ctx.job.id, ctx.attempt)


def _end(ctx: JobContext, state: JobState, code: str, detail: str) -> str:
    """End the attempt failed or cancelled, its subject with it; retried on transient
    errors, and left for the sweeper when the database stays away."""
    job_id, attempt = ctx.job.id, ctx.attempt

    def end() -> str:
        with transaction() as session:
            job = jobs.finish(session, job_id, attempt, state, error_code=code, error_detail=detail)
            if job is None:
                return "lost"
            lifecycle.settle(session, job)
        return str(state)

    return _or_defer(ctx, end, f"end of job {job_id}")


def _requeue(ctx: JobContext, detail: str) -> str:
    """After a transient database error: back to the queue while attempts remain (the
    sweeper's rule), else failed ``DatabaseUnavailable``; cancelled when the user asked."""
    job_id, attempt, settings = ctx.job.id, ctx.attempt, ctx.settings

    def give_back() -> str:
        with transaction() as session:
            job = jobs.get(session, job_id)
            if job.state != JobState.running or job.attempts != attempt:
                return "lost"
            if job.cancel_requested:
                state, code, why = JobState.cancelled, "Cancelled", "cancelled by request"
            elif job.attempts >= settings.max_job_attempts:
                state, code = JobState.failed, "DatabaseUnavailable"
                why = f"database error on the last of {job.attempts} attempts: {detail}"
            else:
                return "requeued" if jobs.requeue(session, job_id, attempt) else "lost"
            ended = jobs.finish(session, job_id, attempt, state, error_code=code, error_detail=why)
            if ended is None:
                return "lost"
            lifecycle.settle(session, ended)
            return str(state)

    return _or_defer(ctx, give_back, f"requeue of job {job_id}")


def _or_defer(ctx: JobContext, write: Callable[[], str], what: str) -> str:
    try:
        return retry_transient(write, bound_s=ctx.settings.db_retry_s, what=what)
    except Exception as exc:
        if not is_transient(exc):
            raise
        log.error("%s: database unavailable; the job is left for the sweeper: %s", what, exc)
        return "deferred"
