from __future__ import annotations

from datetime import datetime
from typing import Any

from pydantic import BaseModel

from app.api.schemas.common import Model
from app.api.schemas.jobs import JobRead
from app.core.enums import SnapshotSource, SnapshotState, TwinUpdate
from app.core.models import Comparison, Job, Snapshot


class SnapshotRead(Model):
    id: str
    environment: str
    seq: int
    state: SnapshotState
    source: SnapshotSource = SnapshotSource.photos  # photos | scan: where its cloud comes from
    created_at: datetime
    reconstructed_at: datetime | None
    n_images: int
    n_detections: int
    upload_bytes: int
    has_cameras: bool
    quality: dict[str, Any]
    job: str | None
    comparison: str | None
    twin_update: TwinUpdate | None = None  # baseline | applied | skipped; None until its turn
    # when retention deleted the photos (the cloud, cameras and detections stay)
    images_deleted_at: datetime | None = None
    links: dict[str, str]

    @classmethod
    def of(cls, snap: Snapshot, job: Job | None, comparison: Comparison | None) -> SnapshotRead:
        links = {"self": f"/v1/snapshots/{snap.id}"}
        if snap.pointcloud_key:
            links["pointcloud"] = f"/v1/snapshots/{snap.id}/pointcloud"
        if job:
            links["job"] = f"/v1/jobs/{job.id}"
        if comparison:
            links["comparison"] = f"/v1/comparisons/{comparison.id}"
        return cls(
            id=snap.id,
            environment=snap.environment_id,
            seq=snap.seq,
            state=snap.state,
            source=SnapshotSource(snap.source or SnapshotSource.photos),
            created_at=snap.created_at,
            reconstructed_at=snap.reconstructed_at,
            n_images=snap.n_images,
            n_detections=snap.n_detections,
            upload_bytes=snap.upload_bytes,
            has_cameras=snap.has_cameras,
            quality=snap.quality or {},
            job=job.id if job else None,
            comparison=comparison.id if comparison else None,
            twin_update=TwinUpdate(snap.twin_update) if snap.twin_update else None,
            images_deleted_at=snap.images_deleted_at,
            links=links,
        )


class SnapshotAccepted(BaseModel):
    snapshot: SnapshotRead
    job: JobRead
