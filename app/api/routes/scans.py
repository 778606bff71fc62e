"""Laser scans: upload an E57, LAS, LAZ or PLY cloud as a snapshot (202 + job)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, BinaryIO

from fastapi import APIRouter, Depends, File, Form, Header, Response, UploadFile, status

from app.api.answers import snapshot_accepted
from app.api.deps import CaptureKey, SessionDep, SettingsDep, StorageDep
from app.api.schemas.common import ERRORS, MALFORMED, ErrorOut
from app.api.schemas.snapshots import SnapshotAccepted
from app.core import auth, scans
from app.core.db import get_read_session_factory

router = APIRouter(tags=["snapshots"], responses=ERRORS)


@dataclass(frozen=True)
class ScanUpload:
    """The scan file (a spooled temporary file, read in chunks), its frame document and the
    optional ``Idempotency-Key``."""

    file: BinaryIO
    frame: str | None
    idempotency_key: str | None


def scan_upload(
    file: Annotated[
        UploadFile, File(description="E57, LAS, LAZ or PLY point cloud (recognised by content)")
    ],
    frame: Annotated[
        str | None,
        Form(
            description='JSON: {"transform": 4×4 env_from_scan, "units": "m"} or '
            '{"markers": true, "units": "m"}; units m, cm, mm, ft, us_ft, in'
        ),
    ] = None,
    idempotency_key: Annotated[str | None, Header(max_length=200)] = None,
) -> ScanUpload:
    """The multipart form and header of a scan upload."""
    return ScanUpload(file.file, frame, idempotency_key)


@router.post(
    "/environments/{environment_id}/scans",
    status_code=status.HTTP_202_ACCEPTED,
    responses={
        **MALFORMED,
        409: {"model": ErrorOut, "description": "Idempotency-Key reused with another scan"},
        413: {"model": ErrorOut, "description": "over max_scan_bytes"},
        415: {"model": ErrorOut, "description": "not an E57, LAS, LAZ or PLY file"},
        422: {
            "model": ErrorOut,
            "description": "TruncatedScan, EmptyScan, InvalidScan, InvalidFrame (not a rigid "
            "4×4, unknown units) or NoMarkerSheet",
        },
        507: {"model": ErrorOut, "description": "storage full: nothing was kept, retry later"},
    },
)
def upload_scan(
    environment_id: str,
    session: SessionDep,
    storage: StorageDep,
    settings: SettingsDep,
    response: Response,
    key: CaptureKey,
    upload: Annotated[ScanUpload, Depends(scan_upload)],
) -> SnapshotAccepted:
    """Upload a laser scan as a snapshot; a job reads it into the environment frame and
    compares it like a photo snapshot."""
    auth.require_environment(key, environment_id)
    result = scans.create_scan_snapshot(
        session,
        storage,
        settings,
        environment_id,
        upload.file,
        upload.frame,
        idempotency_key=upload.idempotency_key,
        lookup=get_read_session_factory(),
    )
    return snapshot_accepted(response, result)
