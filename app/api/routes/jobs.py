"""Jobs: poll state and progress, cancel."""

from __future__ import annotations

import time

from fastapi import APIRouter
from starlette.concurrency import run_in_threadpool

from app.api.deps import CaptureKey, ReadKey, SessionDep
from app.api.schemas.common import ERRORS, conflict
from app.api.schemas.jobs import JobRead
from app.core import auth, jobs
from app.core.db import get_read_session_factory
from app.core.settings import get_settings

router = APIRouter(prefix="/jobs", tags=["jobs"], responses=ERRORS)


class _RecentJobs:
    """Job reads of the last ``ttl_s`` seconds in this process. Workers write a job's
    progress at most every couple of seconds, so a poll answered from here is at most
    ``ttl_s`` older than the database; this process's own cancel replaces the entry."""

    def __init__(self) -> None:
        self._entries: dict[str, tuple[float, JobRead]] = {}

    def get(self, job_id: str, ttl_s: float) -> JobRead | None:
        entry = self._entries.get(job_id)
        if entry is None or time.monotonic() - entry[0] > ttl_s:
            return None
        return entry[1]

    def put(self, job: JobRead) -> None:
        if len(self._entries) > 10_000:
            self._entries.clear()
        self._entries[job.id] = (time.monotonic(), job)


RECENT = _RecentJobs()


@router.get("/{job_id}")
async def get_job(job_id: str, key: ReadKey) -> JobRead:
    """A job's state, stage, progress 0..1 and error."""
    # The hot path of every client that polls: answered from a sub-second cache, else one
    # thread-pool hop for the read instead of one per dependency. A key limited to
    # environments always reads the row, whose environment it is checked against.
    ttl_s = get_settings().job_poll_cache_s
    unlimited = key.environment_ids is None
    cached = RECENT.get(job_id, ttl_s) if ttl_s > 0 and unlimited else None
    if cached is not None:
        return cached
    job = await run_in_threadpool(_read_job, job_id, key)
    RECENT.put(job)
    return job


def _read_job(job_id: str, key: auth.Principal) -> JobRead:
    with get_read_session_factory().begin() as session:
        row = jobs.get(session, job_id)
        if row.environment_id is not None:
            auth.require_environment(key, row.environment_id, detail=f"job {job_id} not found")
        return JobRead.of(row)


@router.post("/{job_id}/cancel", responses=conflict("JobFinished: the job already ended"))
def cancel_job(job_id: str, session: SessionDep, key: CaptureKey) -> JobRead:
    """Cancel a queued job at once, or ask a running one to stop; 409 when already finished.
    Needs a key that reaches the job's environment, or admin (jobs of no environment)."""
    auth.require_job_control(key, job_id, jobs.get(session, job_id).environment_id)
    job = JobRead.of(jobs.cancel(session, job_id))
    RECENT.put(job)
    return job
