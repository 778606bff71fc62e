"""Snapshots: upload a capture (202 + job), read its state, quality and point cloud."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import StreamingResponse

from app.api.deps import ReadKey, SessionDep, StorageDep
from app.api.schemas.common import ERRORS
from app.api.schemas.snapshots import SnapshotRead
from app.core import snapshots
from app.core.errors import Conflict

router = APIRouter(tags=["snapshots"], responses=ERRORS)


@router.get("/snapshots/{snapshot_id}")
def get_snapshot(snapshot_id: str, session: SessionDep, _key: ReadKey) -> SnapshotRead:
    """State, quality figures, its automatic comparison, links to artifacts."""
    snap = snapshots.get(session, snapshot_id)
    return SnapshotRead.of(
        snap,
        snapshots.job_of(session, snap.id),
        snapshots.automatic_comparison_of(session, snap.id),
    )


@router.get(
    "/snapshots/{snapshot_id}/pointcloud",
    response_class=StreamingResponse,
    responses={200: {"content": {"application/octet-stream": {}}}},
)
def get_pointcloud(
    snapshot_id: str, session: SessionDep, storage: StorageDep, _key: ReadKey
) -> StreamingResponse:
    """The reconstructed cloud: binary PLY, coloured, in the environment frame (409 until
    the snapshot is reconstructed)."""
    snap = snapshots.get(session, snapshot_id)
    if not snap.pointcloud_key:
        raise Conflict(
            f"snapshot {snapshot_id} has no point cloud (state {snap.state})",
            code="PointCloudNotReady",
        )
    return StreamingResponse(
        storage.iter_bytes(snap.pointcloud_key),
        media_type="application/octet-stream",
        headers={"Content-Disposition": f'attachment; filename="{snapshot_id}.ply"'},
    )
