"""Jobs: poll state and progress, cancel."""

from __future__ import annotations

from fastapi import APIRouter

from app.api.deps import CaptureKey, ReadKey, SessionDep
from app.api.schemas.common import ERRORS
from app.api.schemas.jobs import JobRead
from app.core import jobs

router = APIRouter(prefix="/jobs", tags=["jobs"], responses=ERRORS)


@router.get("/{job_id}")
def get_job(job_id: str, session: SessionDep, _key: ReadKey) -> JobRead:
    """A job's state, stage, progress 0..1 and error."""
    return JobRead.of(jobs.get(session, job_id))


@router.post("/{job_id}/cancel")
def cancel_job(job_id: str, session: SessionDep, _key: CaptureKey) -> JobRead:
    """Cancel a queued job at once, or ask a running one to stop; 409 when already finished."""
    return JobRead.of(jobs.cancel(session, job_id))
