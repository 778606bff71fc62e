"""A resumable (tus) upload as ``GET /v1/uploads/{id}`` shows it."""

from __future__ import annotations

from datetime import datetime

from pydantic import BaseModel, Field

from app.core.models import ResumableUpload


class UploadError(BaseModel):
    status: int = Field(description="the HTTP status the final PATCH answered")
    code: str
    detail: str


class UploadRead(BaseModel):
    id: str
    environment_id: str
    state: str = Field(description="receiving | processing | completed | failed")
    offset: int = Field(description="bytes received (the length once complete)")
    length: int = Field(description="Upload-Length, bytes")
    filename: str
    idempotency_key: str | None
    created_at: datetime
    expires_at: datetime = Field(description="deleted after this unless written to again")
    snapshot: str | None = Field(description="the snapshot it became, once completed")
    job: str | None = Field(description="that snapshot's job")
    error: UploadError | None = Field(description="why the archive was refused (failed)")

    @classmethod
    def of(cls, upload: ResumableUpload, offset: int) -> UploadRead:
        error = (
            UploadError(
                status=upload.error_status, code=upload.error_code, detail=upload.error_detail
            )
            if upload.error_status is not None and upload.error_code and upload.error_detail
            else None
        )
        return cls(
            id=upload.id,
            environment_id=upload.environment_id,
            state=upload.state,
            offset=offset,
            length=upload.length,
            filename=upload.filename,
            idempotency_key=upload.idempotency_key,
            created_at=upload.created_at,
            expires_at=upload.expires_at,
            snapshot=upload.snapshot_id,
            job=upload.job_id,
            error=error,
        )
