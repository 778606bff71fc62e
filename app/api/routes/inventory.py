"""The inventory of a snapshot: every library object its reconstruction shows."""

from __future__ import annotations

from fastapi import APIRouter

from app.api.deps import ReadKey, SessionDep
from app.api.schemas.common import ERRORS, conflict
from app.api.schemas.inventory import SnapshotObjectRead
from app.core import auth, inventory, snapshots, twin_records

router = APIRouter(tags=["snapshots"], responses=ERRORS)


@router.get(
    "/snapshots/{snapshot_id}/objects",
    responses=conflict(
        "NotInventoried: the snapshot has no inventory (not reconstructed yet, a laser scan, "
        "or the inventory failed)"
    ),
)
def list_objects(snapshot_id: str, session: SessionDep, key: ReadKey) -> list[SnapshotObjectRead]:
    """Every library object the snapshot shows, changed or not: class, 4×4 pose in the
    environment frame (metres), verification, identification metric, the twin instance it
    is and that instance's external id."""
    snap = snapshots.get(session, snapshot_id)
    auth.require_environment(key, snap.environment_id, detail=f"snapshot {snapshot_id} not found")
    inventory.require_inventory(snap)
    rows = inventory.objects_of(session, snap.id)
    platform_ids = twin_records.external_ids(session, (r.instance_id for r in rows))
    return [SnapshotObjectRead.of(row, platform_ids) for row in rows]
