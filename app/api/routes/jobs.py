"""Jobs: poll state and progress, cancel."""

from __future__ import annotations

from fastapi import APIRouter
from starlette.concurrency import run_in_threadpool

from app.api.deps import CaptureKey, ReadKey, SessionDep
from app.api.schemas.common import ERRORS
from app.api.schemas.jobs import JobRead
from app.core import jobs
from app.core.db import get_read_session_factory

router = APIRouter(prefix="/jobs", tags=["jobs"], responses=ERRORS)


@router.get("/{job_id}")
async def get_job(job_id: str, _key: ReadKey) -> JobRead:
    """A job's state, stage, progress 0..1 and error."""
    # The hot path of every client that polls: one thread-pool hop for the read, instead
    # of one per dependency.
    return await run_in_threadpool(_read_job, job_id)


def _read_job(job_id: str) -> JobRead:
    with get_read_session_factory().begin() as session:
        return JobRead.of(jobs.get(session, job_id))


@router.post("/{job_id}/cancel")
def cancel_job(job_id: str, session: SessionDep, _key: CaptureKey) -> JobRead:
    """Cancel a queued job at once, or ask a running one to stop; 409 when already finished."""
    return JobRead.of(jobs.cancel(session, job_id))
