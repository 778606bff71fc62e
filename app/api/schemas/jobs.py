from __future__ import annotations

from datetime import datetime

from app.api.schemas.common import Model
from app.core.enums import JobKind, JobState
from app.core.models import Job


class JobError(Model):
    code: str
    detail: str | None = None


class JobRead(Model):
    id: str
    kind: JobKind
    state: JobState
    stage: str | None
    progress: float
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    cancel_requested: bool
    attempts: int
    error: JobError | None = None
    links: dict[str, str]

    @classmethod
    def of(cls, job: Job) -> JobRead:
        links = {"self": f"/v1/jobs/{job.id}"}
        if job.snapshot_id:
            links["snapshot"] = f"/v1/snapshots/{job.snapshot_id}"
        if job.comparison_id:
            links["comparison"] = f"/v1/comparisons/{job.comparison_id}"
        if job.object_id:
            links["object"] = f"/v1/objects/{job.object_id}"
        if job.environment_id:
            links["environment"] = f"/v1/environments/{job.environment_id}"
        error = JobError(code=job.error_code, detail=job.error_detail) if job.error_code else None
        return cls(
            id=job.id,
            kind=job.kind,
            state=job.state,
            stage=job.stage,
            progress=job.progress,
            created_at=job.created_at,
            started_at=job.started_at,
            finished_at=job.finished_at,
            cancel_requested=job.cancel_requested,
            attempts=job.attempts,
            error=error,
            links=links,
        )
