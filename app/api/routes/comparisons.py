"""Comparison results."""

from __future__ import annotations

from fastapi import APIRouter

from app.api.deps import ReadKey, SessionDep
from app.api.schemas.common import ERRORS
from app.api.schemas.comparisons import ComparisonRead
from app.core import auth, comparisons

router = APIRouter(prefix="/comparisons", tags=["comparisons"], responses=ERRORS)


@router.get("/{comparison_id}")
def get_comparison(comparison_id: str, session: SessionDep, key: ReadKey) -> ComparisonRead:
    """Distances, the cluster × class identification table, and the changes with poses."""
    comparison = comparisons.get(session, comparison_id)
    auth.require_environment(
        key, comparison.environment_id, detail=f"comparison {comparison_id} not found"
    )
    return ComparisonRead.of(comparison)
