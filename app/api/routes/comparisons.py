"""Comparison results."""

from __future__ import annotations

from fastapi import APIRouter

from app.api.deps import ReadKey, SessionDep
from app.api.schemas.common import ERRORS
from app.api.schemas.comparisons import ComparisonRead
from app.core import comparisons

router = APIRouter(prefix="/comparisons", tags=["comparisons"], responses=ERRORS)


@router.get("/{comparison_id}")
def get_comparison(comparison_id: str, session: SessionDep, _key: ReadKey) -> ComparisonRead:
    """Distances, the cluster × class identification table, and the changes with poses."""
    return ComparisonRead.of(comparisons.get(session, comparison_id))
