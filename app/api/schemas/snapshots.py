from __future__ import annotations

from datetime import datetime
from typing import Any
from urllib.parse import quote

from pydantic import BaseModel, Field

from app.api.schemas.common import Model
from app.api.schemas.jobs import JobRead
from app.core.enums import SnapshotSource, SnapshotState, TwinUpdate
from app.core.models import Comparison, Job, Snapshot
from app.core.snapshot_images import PhotoInfo


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
    inventory: dict[str, Any] | None = Field(
        default=None,
        description="the summary of the snapshot's inventory (its objects: GET "
        "/v1/snapshots/{id}/objects): objects (count), options ({preset, ...} it ran with), "
        "supports [{name, plane, height_m, noise_m, area_m2, n_points}], stats (counts, "
        "timings_s), rejected (identified segments left out, each with its reason); or "
        "objects 0 and error {code, detail} when the stage failed. Null: none taken (not "
        "reconstructed yet, a laser scan, or reconstructed before inventories)",
    )
    links: dict[str, str]

    @classmethod
    def of(cls, snap: Snapshot, job: Job | None, comparison: Comparison | None) -> SnapshotRead:
        links = {"self": f"/v1/snapshots/{snap.id}"}
        if snap.pointcloud_key:
            links["pointcloud"] = f"/v1/snapshots/{snap.id}/pointcloud"
        if snap.inventory is not None and "error" not in snap.inventory:
            links["objects"] = f"/v1/snapshots/{snap.id}/objects"
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
            inventory=snap.inventory,
            links=links,
        )


class SnapshotAccepted(BaseModel):
    snapshot: SnapshotRead
    job: JobRead


class CameraRead(BaseModel):
    """A registered photo's camera: ``K`` (3×3, pixels) and ``env_from_cam`` (4×4 row-major,
    metres, OpenCV axes: x right, y down, z forward)."""

    K: list[list[float]]
    env_from_cam: list[list[float]]


class DetectionRead(BaseModel):
    class_name: str
    class_id: int
    box_px: list[float] = Field(description="[x0, y0, x1, y1] pixels of the photo")
    confidence: float | None


class SnapshotImageRead(BaseModel):
    name: str
    width: int
    height: int
    url: str = Field(description="the photo's bytes (410 once retention deleted the photos)")
    registered: bool = Field(description="the reconstruction placed its camera")
    camera: CameraRead | None
    detections: list[DetectionRead]

    @classmethod
    def of(cls, snapshot_id: str, photo: PhotoInfo) -> SnapshotImageRead:
        cam = photo.camera
        return cls(
            name=photo.name,
            width=photo.width,
            height=photo.height,
            url=f"/v1/snapshots/{snapshot_id}/images/{quote(photo.name, safe='')}",
            registered=cam is not None,
            camera=None
            if cam is None
            else CameraRead(K=cam.k.tolist(), env_from_cam=cam.env_from_cam.tolist()),
            detections=[
                DetectionRead(
                    class_name=d.class_name,
                    class_id=d.class_id,
                    box_px=list(d.box_px),
                    confidence=d.confidence,
                )
                for d in photo.detections
            ],
        )
