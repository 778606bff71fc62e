"""The shape every job task has: claim → compute with no open session → persist.

``run_job(job_id, compute, persist, on_failure)``:
1. claim the job in a short transaction (conditional UPDATE; nothing to do if another
   worker has it or it is already final, so a redelivered message is harmless);
2. call ``compute(ctx)`` holding no database session; it reports progress through
   ``ctx.progress`` (which also raises Cancelled when the user cancelled);
3. in one transaction, mark the job succeeded (only if this attempt still owns it: the
   attempt number is a fencing token) and ``persist`` the result, so results are written
   exactly once; on any failure mark the job failed with a code and call ``on_failure``.
"""

from __future__ import annotations

import logging
import os
import shutil
import socket
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

from sqlalchemy.orm import Session

from app.core import jobs
from app.core.db import transaction
from app.core.enums import JobState
from app.core.errors import DomainError
from app.core.models import Job
from app.core.settings import Settings, get_settings
from app.core.storage import LocalStorage
from workers.pipeline.errors import Cancelled, PipelineError
from workers.progress import ProgressReporter

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
    storage: LocalStorage
    settings: Settings


class JobFailure(Exception):
    """Raised by glue code for an expected failure with a code a person can act on."""

    def __init__(self, code: str, detail: str) -> None:
        super().__init__(detail)
        self.code, self.detail = code, detail


def worker_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def run_job(
    job_id: str,
    compute: Callable[[JobContext], R],
    persist: Callable[[Session, JobContext, R], None],
    on_failure: Callable[[Session, Job, str, str], None] | None = None,
) -> str:
    """Run one job to a final state; returns what happened (for logs and tests)."""
    settings = get_settings()
    with transaction() as session:
        attempt = jobs.claim(session, job_id, worker_name())
    if attempt is None:
        return "skipped"
    with transaction() as session:
        job = jobs.get(session, job_id)
    storage = LocalStorage(settings.resolved_storage_dir)
    work_dir = storage.path(f".work/{job_id}")
    work_dir.mkdir(parents=True, exist_ok=True)
    reporter = ProgressReporter(
        job_id, attempt, settings.progress_interval_s, settings.heartbeat_interval_s
    )
    ctx = JobContext(job, attempt, reporter, work_dir, storage, settings)
    try:
        with reporter:
            result = compute(ctx)
            reporter.check_cancelled()
        with transaction() as session:
            if jobs.finish(session, job_id, attempt, JobState.succeeded) is None:
                log.warning("job %s attempt %s lost ownership; result discarded", job_id, attempt)
                return "lost"
            persist(session, ctx, result)
        outcome = "succeeded"
    except Cancelled:
        outcome = _fail(
            job_id, attempt, JobState.cancelled, "Cancelled", "cancelled by request", on_failure
        )
    except (PipelineError, JobFailure, DomainError) as exc:
        outcome = _fail(job_id, attempt, JobState.failed, exc.code, exc.detail, on_failure)
    except Exception as exc:
        log.exception("job %s failed unexpectedly", job_id)
        outcome = _fail(
            job_id,
            attempt,
            JobState.failed,
            "InternalError",
            f"{type(exc).__name__}: {exc}",
            on_failure,
        )
    if outcome != "lost":
        shutil.rmtree(work_dir, ignore_errors=True)
    return outcome


def _fail(
    job_id: str,
    attempt: int,
    state: JobState,
    code: str,
    detail: str,
    on_failure: Callable[[Session, Job, str, str], None] | None,
) -> str:
    with transaction() as session:
        job = jobs.finish(session, job_id, attempt, state, error_code=code, error_detail=detail)
        if job is None:
            return "lost"
        if on_failure is not None:
            on_failure(session, job, code, detail)
        if state == JobState.failed:
            jobs.record_failed(session, job)
    return str(state)


def on_failure_of(kind: str) -> Callable[[Session, Job, str, str], None] | None:
    """The failure handler of a job kind (marks its snapshot, comparison or object failed),
    for failures decided outside the task, such as the sweeper's."""
    from workers import comparison, objects, snapshot

    handlers: dict[str, Callable[[Session, Job, str, str], None]] = {
        "snapshot": snapshot.on_failure,
        "comparison": comparison.on_failure,
        "object": objects.on_failure,
    }
    return handlers.get(str(kind))
