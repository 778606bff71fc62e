"""Comparison results, and retrying a comparison that failed."""

from __future__ import annotations

from fastapi import APIRouter, Response, status
from sqlalchemy.orm import Session

from app.api.deps import AdminKey, ReadKey, SessionDep, StorageDep
from app.api.schemas.common import ERRORS, ErrorOut, conflict
from app.api.schemas.comparisons import (
    ChangeViewRead,
    ClusterPointsRead,
    ClustersRead,
    ComparisonRead,
)
from app.core import auth, change_views, comparisons, twin_records
from app.core.models import Comparison

router = APIRouter(prefix="/comparisons", tags=["comparisons"], responses=ERRORS)


def _reachable(session: Session, comparison_id: str, key: auth.Principal) -> Comparison:
    """The comparison; 404 when unknown or of an environment ``key`` does not reach (the
    same answer for both)."""
    comparison = comparisons.get(session, comparison_id)
    auth.require_environment(
        key, comparison.environment_id, detail=f"comparison {comparison_id} not found"
    )
    return comparison


@router.get("/{comparison_id}")
def get_comparison(comparison_id: str, session: SessionDep, key: ReadKey) -> ComparisonRead:
    """Distances, the cluster × class identification table, and the changes with poses."""
    comparison = _reachable(session, comparison_id, key)
    return ComparisonRead.of(
        comparison, twin_records.comparison_external_ids(session, [comparison])
    )


@router.post(
    "/{comparison_id}/retry",
    status_code=status.HTTP_202_ACCEPTED,
    responses={
        202: {"description": "queued again with a new job (Location: the job)"},
        409: {
            "model": ErrorOut,
            "description": "ComparisonNotRetryable: it did not fail and was not cancelled; "
            "SnapshotNotReconstructed: one of its snapshots is gone",
        },
    },
)
def retry_comparison(
    comparison_id: str, session: SessionDep, response: Response, key: AdminKey
) -> ComparisonRead:
    """Run a failed or cancelled comparison again; a failed automatic one holds its
    environment's twin (status blocked) until it succeeds."""
    _reachable(session, comparison_id, key)
    comparison = comparisons.retry(session, comparison_id)
    response.headers["Location"] = f"/v1/jobs/{comparison.job_id}"
    return ComparisonRead.of(comparison)


_CLUSTERS_CONFLICT = conflict(
    "ComparisonNotSucceeded: not finished or failed; ClustersNotStored: made before cluster "
    "points were kept (run it again); ClustersUnreadable: the stored file is damaged"
)


@router.get("/{comparison_id}/clusters", responses=_CLUSTERS_CONFLICT)
def get_clusters(
    comparison_id: str, session: SessionDep, storage: StorageDep, key: ReadKey
) -> ClustersRead:
    """The change clusters' points (environment frame, metres; at most 20 000 a cluster)
    with their side and change, for drawing."""
    comparison = _reachable(session, comparison_id, key)
    return ClustersRead(
        clusters=[
            ClusterPointsRead(
                id=c.id,
                side="added" if c.side == "added" else "removed",
                change_id=c.change_id,
                n_points=c.n_points,
                positions=[round(float(v), 4) for v in c.points_env.reshape(-1)],
            )
            for c in change_views.stored_clusters(session, storage, comparison)
        ]
    )


@router.get(
    "/{comparison_id}/changes/{change_id}/views",
    responses=conflict(
        "ComparisonNotSucceeded, ClustersNotStored, ClustersUnreadable (as for /clusters); "
        "CamerasUnreadable, PointCloudNotReady, PointCloudUnreadable: the snapshot's "
        "cameras or cloud cannot be read"
    ),
)
def get_change_views(
    comparison_id: str, change_id: str, session: SessionDep, storage: StorageDep, key: ReadKey
) -> list[ChangeViewRead]:
    """Every photo that saw the change's cluster: the cluster's re-projected outline and
    box, and the detection of the change's class that overlaps it best with its IoU."""
    comparison = _reachable(session, comparison_id, key)
    return [
        ChangeViewRead(
            image=v.image,
            outline_px=v.outline_px,
            box_px=v.box_px,
            detection_box_px=v.detection_box_px,
            iou=v.iou,
            counted=v.counted,
        )
        for v in change_views.views(session, storage, comparison, change_id)
    ]
