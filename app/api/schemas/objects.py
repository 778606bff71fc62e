from __future__ import annotations

from datetime import datetime
from typing import Any

from app.api.schemas.common import Model
from app.api.schemas.jobs import JobRead
from app.core.enums import ObjectState
from app.core.models import Job, LibraryObject


class ObjectRead(Model):
    id: str
    name: str
    state: ObjectState
    units: str
    filename: str
    size_bytes: int
    diameter_m: float | None
    n_points: int | None
    symmetry: dict[str, Any] | None
    symmetry_requested: dict[str, Any]
    created_at: datetime
    job: JobRead | None = None

    @classmethod
    def of(cls, obj: LibraryObject, job: Job | None) -> ObjectRead:
        out = cls.model_validate(obj)
        out.job = JobRead.of(job) if job else None
        return out
