"""The FastAPI application: ``create_app()`` wires routers, one error handler and the
lifespan (bootstrap admin key)."""

from __future__ import annotations

import logging
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from sqlalchemy.exc import DataError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match

from app.api import metrics as metrics_routes
from app.api.console import ConsoleFiles
from app.api.json_guard import JsonGuard
from app.api.limits import BodyGuard
from app.api.routes import (
    comparisons,
    environments,
    health,
    inventory,
    jobs,
    keys,
    objects,
    scans,
    snapshots,
    twin_objects,
    uploads,
    webhooks,
)
from app.core import auth, ingest
from app.core import uploads as resumable
from app.core.db import get_session_factory
from app.core.errors import DomainError
from app.core.settings import get_settings
from app.core.storage import open_storage

log = logging.getLogger("twindelta")

API_DESCRIPTION = """
twindelta keeps a factory's digital twin in step with the shop floor. Capture stations
upload photo sets with YOLO detections; workers reconstruct a point cloud, compare it with the
environment's previous snapshot, identify which library objects were added, removed, moved or
swapped, estimate their 6-DoF poses (4×4 `env_from_object`, metres) and notify the twin
platform by webhook. Every endpoint except `/healthz` and `/readyz` needs
`Authorization: Bearer <api key>`. Errors are `{"error": code, "detail": text}`.
"""


@asynccontextmanager
async def lifespan(_app: FastAPI) -> AsyncIterator[None]:
    settings = get_settings()
    if settings.bootstrap_admin_key:
        with get_session_factory().begin() as session:
            if auth.bootstrap_admin_key(session, settings.bootstrap_admin_key):
                log.info("created the bootstrap admin key")
    # Staging folders of uploads whose API process died (killed mid-upload) go at once.
    storage = open_storage(settings)
    ingest.sweep_staging(storage)
    resumable.sweep_spools(storage, time.time() - settings.stale_files_after_s)
    yield


def _error(status: int, code: str, detail: str) -> JSONResponse:
    return JSONResponse(status_code=status, content={"error": code, "detail": detail})


def _allowed_methods(request: Request) -> list[str]:
    """Every method some route serves at the request's path (asked of the router itself,
    so included routers and path parameters count as they do for dispatch)."""
    routes = request.app.router.routes
    return [
        method
        for method in ("GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS")
        if any(r.matches({**request.scope, "method": method})[0] == Match.FULL for r in routes)
    ]


def create_app() -> FastAPI:
    app = FastAPI(
        title="twindelta",
        version="0.1.0",
        description=API_DESCRIPTION,
        lifespan=lifespan,
    )

    @app.exception_handler(DomainError)
    async def domain_error(_request: Request, exc: DomainError) -> JSONResponse:
        response = _error(exc.status_code, exc.code, exc.detail)
        response.headers.update(exc.headers or {})  # e.g. Retry-After on a 429
        return response

    @app.exception_handler(DataError)
    async def data_error(_request: Request, exc: DataError) -> JSONResponse:
        # What the database refuses to store, found past the API's own checks (a NUL
        # character in a form field or a path, a number out of a column's range): the
        # request's fault, so a 422 with the database's reason, not a 500.
        reason = str(exc.orig).splitlines()[0] if exc.orig is not None else "invalid value"
        log.info("database refused a value: %s", reason)
        return _error(422, "InvalidInput", f"a value the database cannot store: {reason}")

    @app.exception_handler(RequestValidationError)
    async def validation_error(_request: Request, exc: RequestValidationError) -> JSONResponse:
        parts = []
        for err in exc.errors():
            where = ".".join(str(p) for p in err.get("loc", ()) if p != "body")
            parts.append(f"{where}: {err.get('msg')}" if where else str(err.get("msg")))
        return _error(422, "InvalidInput", "; ".join(parts) or "invalid request")

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        codes = {
            400: "BadRequest",
            401: "Unauthorized",
            404: "NotFound",
            405: "MethodNotAllowed",
        }
        response = _error(exc.status_code, codes.get(exc.status_code, "HTTPError"), str(exc.detail))
        response.headers.update(exc.headers or {})
        if exc.status_code == 405:
            # Allow lists every method of the resource (Starlette names only the first route
            # whose path matched: POST for /v1/environments, which also has GET).
            response.headers["Allow"] = ", ".join(_allowed_methods(request))
        return response

    app.add_middleware(JsonGuard)
    app.add_middleware(BodyGuard)  # key and size checked before a body is read
    app.add_middleware(uploads.TusHeaders)  # Tus-Resumable on /v1/uploads, 412 otherwise
    app.add_middleware(metrics_routes.MetricsMiddleware)
    app.include_router(health.router)
    app.include_router(metrics_routes.router)
    routers = (
        keys,
        objects,
        environments,
        twin_objects,
        snapshots,
        inventory,
        scans,
        uploads,
        jobs,
        comparisons,
        webhooks,
    )
    for module in routers:
        app.include_router(module.router, prefix="/v1")
    app.mount("/ui", ConsoleFiles(get_settings().resolved_console_dir), name="console")
    return app
