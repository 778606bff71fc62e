"""Snapshots: upload a capture (202 + job), read its state, quality and point cloud."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from fastapi import APIRouter, Depends, File, Header, Query, Request, Response, UploadFile, status
from fastapi.responses import FileResponse, StreamingResponse

from app.api import negotiate
from app.api.answers import snapshot_accepted
from app.api.deps import AdminKey, CaptureKey, ReadKey, SessionDep, SettingsDep, StorageDep
from app.api.schemas.common import ERRORS, MALFORMED, ErrorOut, conflict
from app.api.schemas.exports import (
    BINARY,
    CLOUD_MEDIA_TYPES,
    LAZ_MEDIA_TYPE,
    PLY_MEDIA_TYPE,
    CloudFormat,
)
from app.api.schemas.snapshots import SnapshotAccepted, SnapshotImageRead, SnapshotRead
from app.core import auth, ingest, retention, snapshot_images, snapshots
from app.core.db import get_read_session_factory
from app.core.errors import Conflict, InvalidInput
from app.core.export import decimate, laz, twin_scene
from app.core.models import Snapshot

router = APIRouter(tags=["snapshots"], responses=ERRORS)

# The multipart parser's own ceiling; the configured limits (max_upload_files, ...) are
# checked by the ingest service and are normally much lower.
FORM_MAX_FILES = 10_000


def _parts(files: list[UploadFile] | None) -> list[ingest.UploadPart]:
    return [ingest.UploadPart(f.filename or "", f.file) for f in files or []]


@dataclass(frozen=True)
class CaptureUpload:
    """The files of one capture upload and its optional ``Idempotency-Key``."""

    files: ingest.UploadFiles
    idempotency_key: str | None


def capture_upload(
    images: Annotated[list[UploadFile] | None, File(description="JPEG or PNG photos")] = None,
    detections: Annotated[
        list[UploadFile] | None, File(description="YOLO .txt files, one per image stem")
    ] = None,
    cameras: Annotated[UploadFile | None, File(description="optional cameras.json")] = None,
    archive: Annotated[
        UploadFile | None, File(description=".zip, .tar or .tar.gz holding the same files")
    ] = None,
    idempotency_key: Annotated[str | None, Header(max_length=200)] = None,
) -> CaptureUpload:
    """The multipart form and header of a capture upload (these fields, in this order, are
    the request body in the OpenAPI document; a bad header is reported before a bad file)."""
    files = ingest.UploadFiles(
        images=_parts(images),
        detections=_parts(detections),
        cameras=ingest.UploadPart(cameras.filename or "", cameras.file) if cameras else None,
        archive=ingest.UploadPart(archive.filename or "", archive.file) if archive else None,
    )
    return CaptureUpload(files, idempotency_key)


@router.post(
    "/environments/{environment_id}/snapshots",
    status_code=status.HTTP_202_ACCEPTED,
    form_limits={"max_files": FORM_MAX_FILES},
    responses={
        **MALFORMED,
        409: {"model": ErrorOut, "description": "Idempotency-Key reused with other files"},
        413: {"model": ErrorOut, "description": "over a file, byte, pixel or line limit"},
        415: {"model": ErrorOut, "description": "unsupported file type"},
        507: {"model": ErrorOut, "description": "storage full: nothing was kept, retry later"},
    },
)
def upload_snapshot(
    environment_id: str,
    session: SessionDep,
    storage: StorageDep,
    settings: SettingsDep,
    response: Response,
    key: CaptureKey,
    upload: Annotated[CaptureUpload, Depends(capture_upload)],
) -> SnapshotAccepted:
    """Upload a capture (loose files or one archive); a job reconstructs and compares it."""
    auth.require_environment(key, environment_id)
    result = ingest.create_snapshot(
        session,
        storage,
        settings,
        environment_id,
        upload.files,
        idempotency_key=upload.idempotency_key,
        # Reads in short sessions of their own: this request's session takes the database's
        # write lock (SQLite) only for the insert, not while the files are checked.
        lookup=get_read_session_factory(),
    )
    return snapshot_accepted(response, result)


@router.get("/snapshots/{snapshot_id}")
def get_snapshot(snapshot_id: str, session: SessionDep, key: ReadKey) -> SnapshotRead:
    """State, quality figures, its automatic comparison, links to artifacts."""
    snap = snapshots.get(session, snapshot_id)
    auth.require_environment(key, snap.environment_id, detail=f"snapshot {snapshot_id} not found")
    return SnapshotRead.of(
        snap,
        snapshots.job_of(session, snap.id),
        snapshots.automatic_comparison_of(session, snap.id),
    )


@router.delete(
    "/snapshots/{snapshot_id}",
    status_code=status.HTTP_204_NO_CONTENT,
    responses={
        409: {
            "model": ErrorOut,
            "description": "a job using it is queued or running (JobsActive), or it is the "
            "environment's newest reconstructed snapshot (SnapshotInUse)",
        }
    },
)
def delete_snapshot(
    snapshot_id: str, session: SessionDep, storage: StorageDep, key: AdminKey
) -> Response:
    """Delete the snapshot's files, images, jobs and the comparisons it took part in; the
    twin's history keeps its poses (204; see docs/operations.md)."""
    snap = snapshots.get(session, snapshot_id)
    auth.require_environment(key, snap.environment_id, detail=f"snapshot {snapshot_id} not found")
    retention.delete_snapshot(session, storage, snapshot_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)


def _cloud_key(snap: Snapshot) -> str:
    """The storage key of the snapshot's cloud; 409 PointCloudNotReady without one."""
    if not snap.pointcloud_key:
        raise Conflict(
            f"snapshot {snap.id} has no point cloud (state {snap.state})",
            code="PointCloudNotReady",
        )
    return snap.pointcloud_key


@router.get(
    "/snapshots/{snapshot_id}/pointcloud",
    response_class=StreamingResponse,
    responses={
        200: {
            "description": "binary PLY, or LAZ (format=laz or Accept: application/vnd.laszip); "
            "with max_points: X-Total-Points, the points of the full cloud",
            "content": {PLY_MEDIA_TYPE: BINARY, LAZ_MEDIA_TYPE: BINARY},
            "headers": {"X-Total-Points": {"schema": {"type": "integer"}}},
        },
        406: {"model": ErrorOut, "description": "Accept allows neither PLY nor LAZ"},
        **conflict(
            "PointCloudNotReady: the snapshot is not reconstructed (yet); "
            "PointCloudUnreadable: the stored cloud cannot be converted"
        ),
        507: {"model": ErrorOut, "description": "storage full: the LAZ could not be written"},
    },
)
def get_pointcloud(
    snapshot_id: str,
    request: Request,
    session: SessionDep,
    storage: StorageDep,
    key: ReadKey,
    format: Annotated[
        CloudFormat | None,
        Query(description="ply or laz; overrides Accept (default: by Accept, else ply)"),
    ] = None,
    max_points: Annotated[
        int | None,
        Query(
            ge=decimate.MIN_POINTS,
            le=decimate.MAX_POINTS,
            description="at most this many points (N rounded down to 1, 1.25, 1.5, 2, 2.5, "
            "3, 4, 5, 6 or 8 × 10^k), drawn evenly with a fixed seed (the same N gives the "
            "same file; a smaller N a subset of a larger): binary little-endian PLY, float x "
            "y z and uchar red green blue, made once and kept (for a browser)",
        ),
    ] = None,
) -> Response:
    """The reconstructed cloud in the environment frame: binary PLY, coloured, or LAZ
    (converted once, then kept); with ``max_points`` a decimated PLY; 409 until the
    snapshot is reconstructed."""
    snap = snapshots.get(session, snapshot_id)
    auth.require_environment(key, snap.environment_id, detail=f"snapshot {snapshot_id} not found")
    if max_points is not None:
        cloud_key = _cloud_key(snap)
        if format == CloudFormat.laz:
            raise InvalidInput("max_points: a decimated cloud is PLY only; leave out format=laz")
        cached = decimate.ensure_decimated(storage, cloud_key, max_points)
        return FileResponse(
            storage.local_file(cached.key),
            media_type=PLY_MEDIA_TYPE,
            filename=f"{snapshot_id}-{cached.n_points}.ply",
            headers={
                "X-Total-Points": str(cached.total_points),
                "Cache-Control": "private, max-age=3600",
            },
        )
    chosen = (
        format
        or CLOUD_MEDIA_TYPES[
            negotiate.choose(request.headers.get("accept"), list(CLOUD_MEDIA_TYPES))
        ]
    )
    cloud_key = _cloud_key(snap)
    if chosen == CloudFormat.laz:
        laz_key = laz.ensure_laz(storage, cloud_key, twin_scene.generator())
        return StreamingResponse(
            storage.iter_bytes(laz_key),
            media_type=LAZ_MEDIA_TYPE,
            headers={
                "Content-Disposition": f'attachment; filename="{snapshot_id}.laz"',
                "Vary": "Accept",
            },
        )
    return StreamingResponse(
        storage.iter_bytes(cloud_key),
        media_type=PLY_MEDIA_TYPE,
        headers={
            "Content-Disposition": f'attachment; filename="{snapshot_id}.ply"',
            "Vary": "Accept",
        },
    )


@router.get("/snapshots/{snapshot_id}/images")
def list_images(
    snapshot_id: str, session: SessionDep, storage: StorageDep, key: ReadKey
) -> list[SnapshotImageRead]:
    """The snapshot's photos by name: size, the camera the reconstruction gave it (K and
    env_from_cam; null when not registered or not reconstructed yet) and the detector's
    boxes in pixels."""
    snap = snapshots.get(session, snapshot_id)
    auth.require_environment(key, snap.environment_id, detail=f"snapshot {snapshot_id} not found")
    return [
        SnapshotImageRead.of(snap.id, photo)
        for photo in snapshot_images.photos(session, storage, snap)
    ]


@router.get(
    "/snapshots/{snapshot_id}/images/{name}",
    response_class=FileResponse,
    responses={
        200: {
            "description": "the photo as uploaded",
            "content": {"image/jpeg": BINARY, "image/png": BINARY},
        },
        410: {"model": ErrorOut, "description": "ImagesDeleted: retention deleted the photos"},
    },
)
def get_image(
    snapshot_id: str, name: str, session: SessionDep, storage: StorageDep, key: ReadKey
) -> Response:
    """One photo's bytes with its media type (404 for a name the snapshot lacks, 410 once
    the retention policy deleted its photos)."""
    snap = snapshots.get(session, snapshot_id)
    auth.require_environment(key, snap.environment_id, detail=f"snapshot {snapshot_id} not found")
    file_key, media_type = snapshot_images.photo_file(session, storage, snap, name)
    headers = {"Cache-Control": "private"}
    local = storage.cached_file(file_key)
    if local is not None:
        return FileResponse(local, media_type=media_type, headers=headers)
    return StreamingResponse(storage.iter_bytes(file_key), media_type=media_type, headers=headers)
