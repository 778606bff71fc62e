"""Request dependencies as ``Annotated`` aliases: a session that owns the transaction, the
settings, storage, and API keys by scope (with a per-process limit on unknown keys)."""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Iterator
from typing import Annotated, Any

from fastapi import Depends, Request
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool
from starlette.datastructures import Headers

from app.core import auth
from app.core.auth import Principal
from app.core.db import get_read_session_factory, get_session_factory
from app.core.enums import Scope
from app.core.errors import Unauthorized
from app.core.settings import Settings, get_settings
from app.core.storage import Storage, open_storage


def get_session(request: Request) -> Iterator[Session]:
    """One transaction per request: committed when the route returns, rolled back on error.
    GET and HEAD requests get a read-only transaction."""
    read_only = request.method in {"GET", "HEAD"}
    factory = get_read_session_factory() if read_only else get_session_factory()
    with factory.begin() as session:
        yield session


def get_storage(settings: Annotated[Settings, Depends(get_settings)]) -> Storage:
    return open_storage(settings)


# scope="function": the transaction commits before the response is sent, so a client that
# got 201/202 can read what it created at once (and a failed commit is never answered 2xx).
SessionDep = Annotated[Session, Depends(get_session, scope="function")]
SettingsDep = Annotated[Settings, Depends(get_settings)]
StorageDep = Annotated[Storage, Depends(get_storage)]


def bearer(headers: Headers) -> str | None:
    """The token of an ``Authorization: Bearer <token>`` header, or None."""
    scheme, _, token = headers.get("authorization", "").partition(" ")
    return token.strip() if scheme.lower() == "bearer" and token.strip() else None


def _client(request: Request) -> str:
    return request.client.host if request.client else "unknown"


def key_limiter(app: Any) -> auth.FailedKeyLimiter:
    """The app's count of unknown keys by client address (one per app: per API process)."""
    limiter: auth.FailedKeyLimiter | None = getattr(app.state, "failed_keys", None)
    if limiter is None:
        limiter = app.state.failed_keys = auth.FailedKeyLimiter()
    return limiter


async def authenticate_request(
    app: Any, client: str, token: str | None, scope: Scope | None
) -> Principal:
    """The caller of a request to ``app`` from ``client`` with ``token`` holding ``scope``
    (None: any valid key). 429 while ``client`` is over its limit of unknown keys (a
    request with no key is not a guess and gets its 401); otherwise one indexed lookup in a
    short session of its own, off the event loop, every request (no cache: a revocation
    made by any process is refused at once)."""
    settings = get_settings()
    limit, window_s = settings.auth_failure_limit, settings.auth_failure_window_s
    limiter = key_limiter(app)
    if token:
        limiter.check(client, limit=limit, window_s=window_s)
    try:
        return await run_in_threadpool(_authenticate, token, scope)
    except Unauthorized:
        if token:
            limiter.record_failure(client, limit=limit, window_s=window_s)
        raise


def _require(scope: Scope) -> Callable[[Request], Awaitable[Principal]]:
    async def check(request: Request) -> Principal:
        # BodyGuard already looked the key up for a request with a body (before reading it)
        known: Principal | None = getattr(request.state, "principal", None)
        if known is not None:
            return auth.require_scope(known, scope)
        return await authenticate_request(
            request.app, _client(request), bearer(request.headers), scope
        )

    return check


async def _any_key(request: Request) -> Principal:
    known: Principal | None = getattr(request.state, "principal", None)
    if known is not None:
        return known
    return await authenticate_request(request.app, _client(request), bearer(request.headers), None)


def _authenticate(token: str | None, scope: Scope | None) -> Principal:
    with get_read_session_factory()() as session:
        return auth.authenticate(session, token, scope)


AnyKey = Annotated[Principal, Depends(_any_key)]  # any valid key, whatever its scopes
ReadKey = Annotated[Principal, Depends(_require(Scope.read))]
CaptureKey = Annotated[Principal, Depends(_require(Scope.capture))]
AdminKey = Annotated[Principal, Depends(_require(Scope.admin))]
MetricsKey = Annotated[Principal, Depends(_require(Scope.metrics))]
