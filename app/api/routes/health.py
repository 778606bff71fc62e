"""Liveness and readiness; the only endpoints without a key."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import JSONResponse
from sqlalchemy import text

from app.api.deps import SettingsDep, StorageDep
from app.api.schemas.common import Readiness
from app.core.db import get_read_session_factory

router = APIRouter(tags=["health"])


@router.get("/healthz")
def healthz() -> dict[str, str]:
    """The process is up."""
    return {"status": "ok"}


@router.get(
    "/readyz",
    response_model=None,
    responses={
        200: {"model": Readiness, "description": "ready"},
        503: {"model": Readiness, "description": "the database or storage is not ready"},
    },
)
def readyz(settings: SettingsDep, storage: StorageDep) -> dict[str, object] | JSONResponse:
    """The database answers and storage is writable; 503 otherwise."""
    checks: dict[str, str] = {}
    try:
        with get_read_session_factory().begin() as session:
            session.execute(text("SELECT 1"))
        checks["database"] = "ok"
    except Exception as exc:
        checks["database"] = f"error: {type(exc).__name__}"
    try:
        storage.check()  # S3: the bucket answers and this host's scratch is writable
        checks["storage"] = "ok"
    except OSError as exc:
        checks["storage"] = f"error: {exc.strerror}"
    ok = all(v == "ok" for v in checks.values())
    body: dict[str, object] = {"status": "ok" if ok else "unavailable", "checks": checks}
    return body if ok else JSONResponse(status_code=503, content=body)
