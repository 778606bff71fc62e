"""Request dependencies as ``Annotated`` aliases: a session that owns the transaction, the
settings, storage, and API keys by scope."""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Iterator
from typing import Annotated

from fastapi import Depends, Request
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool

from app.core import auth
from app.core.auth import Principal
from app.core.db import get_read_session_factory, get_session_factory
from app.core.enums import Scope
from app.core.settings import Settings, get_settings
from app.core.storage import LocalStorage


def get_session(request: Request) -> Iterator[Session]:
    """One transaction per request: committed when the route returns, rolled back on error.
    GET and HEAD requests get a read-only transaction."""
    read_only = request.method in {"GET", "HEAD"}
    factory = get_read_session_factory() if read_only else get_session_factory()
    with factory.begin() as session:
        yield session


def get_storage(settings: Annotated[Settings, Depends(get_settings)]) -> LocalStorage:
    return LocalStorage(settings.resolved_storage_dir)


# scope="function": the transaction commits before the response is sent, so a client that
# got 201/202 can read what it created at once (and a failed commit is never answered 2xx).
SessionDep = Annotated[Session, Depends(get_session, scope="function")]
SettingsDep = Annotated[Settings, Depends(get_settings)]
StorageDep = Annotated[LocalStorage, Depends(get_storage)]


def _bearer(request: Request) -> str | None:
    header = request.headers.get("authorization", "")
    scheme, _, token = header.partition(" ")
    return token.strip() if scheme.lower() == "bearer" and token.strip() else None


def _require(scope: Scope) -> Callable[[Request], Awaitable[Principal]]:
    async def check(request: Request) -> Principal:
        # Async, so a cached key costs no thread-pool hop; a cache miss runs one indexed
        # lookup in a short session of its own, off the event loop.
        token = _bearer(request)
        principal = auth.cached(token, scope)
        if principal is not None:
            return principal
        return await run_in_threadpool(_authenticate, token, scope)

    return check


def _authenticate(token: str | None, scope: Scope) -> Principal:
    with get_read_session_factory()() as session:
        return auth.authenticate(session, token, scope)


ReadKey = Annotated[Principal, Depends(_require(Scope.read))]
CaptureKey = Annotated[Principal, Depends(_require(Scope.capture))]
AdminKey = Annotated[Principal, Depends(_require(Scope.admin))]
