"""Comparison results, and retrying a comparison that failed."""

from __future__ import annotations

from fastapi import APIRouter, Response, status

from app.api.deps import AdminKey, ReadKey, SessionDep
from app.api.schemas.common import ERRORS, ErrorOut
from app.api.schemas.comparisons import ComparisonRead
from app.core import auth, comparisons, twin_records

router = APIRouter(prefix="/comparisons", tags=["comparisons"], responses=ERRORS)


@router.get("/{comparison_id}")
def get_comparison(comparison_id: str, session: SessionDep, key: ReadKey) -> ComparisonRead:
    """Distances, the cluster × class identification table, and the changes with poses."""
    comparison = comparisons.get(session, comparison_id)
    auth.require_environment(
        key, comparison.environment_id, detail=f"comparison {comparison_id} not found"
    )
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
    comparison = comparisons.get(session, comparison_id)
    auth.require_environment(
        key, comparison.environment_id, detail=f"comparison {comparison_id} not found"
    )
    comparison = comparisons.retry(session, comparison_id)
    response.headers["Location"] = f"/v1/jobs/{comparison.job_id}"
    return ComparisonRead.of(comparison)
