"""API keys: random tokens shown once, stored as SHA-256 hashes, with scopes and optionally
limited to environments.

Scopes: ``capture`` uploads snapshots (and cancels its environments' jobs), ``read`` reads
everything, ``metrics`` reads ``/metrics`` only, ``admin`` manages objects, environments,
webhooks and keys and implies the other three. ``read`` implies ``metrics`` for keys that
reach every environment.

A key with ``environment_ids`` reaches those environments only: anything of another
environment answers 404, exactly as an id that does not exist (so a capture station learns
nothing about other sites), and lists leave it out. Admin and metrics keys always reach every
environment (both see data of all of them), so they cannot be limited.

Every request looks its key up in the database (one indexed query): there is no cache of
valid keys, so a revocation committed by any API process is refused by every other one on
its next request.
"""

from __future__ import annotations

import hashlib
import math
import secrets
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.core.enums import Scope
from app.core.errors import (
    Conflict,
    Forbidden,
    InvalidInput,
    NotFound,
    TooManyRequests,
    Unauthorized,
)
from app.core.models import ApiKey, Environment, new_id, utcnow

KEY_PREFIX = "td_"
IMPLIED_SCOPES: dict[Scope, set[Scope]] = {
    Scope.admin: {Scope.admin, Scope.read, Scope.capture, Scope.metrics},
    Scope.read: {Scope.read, Scope.metrics},
    Scope.capture: {Scope.capture},
    Scope.metrics: {Scope.metrics},
}
# Scopes whose keys see every environment's data: they cannot be limited to environments.
UNLIMITED_SCOPES = {Scope.admin, Scope.metrics}


def hash_key(token: str) -> str:
    """Hex SHA-256 of a token. Tokens carry 256 random bits, so no salt or stretching is
    needed; a lookup by hash is constant-time with respect to the secret."""
    return hashlib.sha256(token.encode()).hexdigest()


def key_label(key_id: str) -> str:
    """The non-secret id stored as a key's ``prefix``: ``td_`` and 8 hex digits of its id."""
    return KEY_PREFIX + key_id.replace("-", "")[:8]


def effective_scopes(scopes: Iterable[str]) -> set[Scope]:
    out: set[Scope] = set()
    for name in scopes:
        out |= IMPLIED_SCOPES[Scope(name)]
    return out


def _environment_list(session: Session, ids: list[str], scopes: set[Scope]) -> list[str]:
    if not ids:
        raise InvalidInput(
            "environment_ids: give at least one environment id, or null for every environment"
        )
    unlimited = sorted(UNLIMITED_SCOPES & scopes)
    if unlimited:
        raise InvalidInput(
            f"environment_ids: {', '.join(unlimited)} keys reach every environment and cannot "
            "be limited; give such a key no environment_ids"
        )
    wanted = sorted(set(ids))
    found = set(session.scalars(select(Environment.id).where(Environment.id.in_(wanted))))
    missing = [i for i in wanted if i not in found]
    if missing:
        raise InvalidInput(f"environment_ids: unknown environment {', '.join(missing)}")
    return wanted


def create_key(
    session: Session,
    name: str,
    scopes: list[str],
    token: str | None = None,
    environment_ids: list[str] | None = None,
) -> tuple[ApiKey, str]:
    """Create a key; returns the row and the plain token (shown once, never stored).

    A generated token is ``td_<8 hex>_<43 url-safe characters>``: the first part is the
    key's non-secret id (stored as ``prefix``), the rest its 256-bit secret. A given
    ``token`` (the bootstrap key) is stored only as its hash."""
    try:
        parsed = sorted({Scope(s) for s in scopes})
    except ValueError as exc:
        raise InvalidInput(
            f"unknown scope in {scopes}; use capture, read, metrics or admin"
        ) from exc
    if not parsed:
        raise InvalidInput("a key needs at least one scope")
    envs = (
        None
        if environment_ids is None
        else _environment_list(session, environment_ids, set(parsed))
    )
    key_id = new_id()
    label = key_label(key_id)
    token = token or f"{label}_{secrets.token_urlsafe(32)}"
    row = ApiKey(
        id=key_id,
        name=name,
        prefix=label,
        key_hash=hash_key(token),
        scopes=list(parsed),
        environment_ids=envs,
    )
    session.add(row)
    session.flush()
    return row, token


@dataclass(frozen=True)
class Principal:
    """Who is calling: the key's id, name, scopes and environments (no secret)."""

    key_id: str
    name: str
    scopes: tuple[str, ...]
    environment_ids: tuple[str, ...] | None = None  # None: every environment

    def holds(self, scope: Scope) -> bool:
        granted = effective_scopes(self.scopes)
        if self.environment_ids is not None:
            granted -= UNLIMITED_SCOPES  # /metrics counts every environment's jobs
        return scope in granted


def authenticate(session: Session, token: str | None, needed: Scope | None) -> Principal:
    """The caller for ``token`` if it holds scope ``needed`` (None: any valid key); 401 when
    the key is missing, unknown or revoked, 403 when it lacks the scope. One query by the
    unique hash, every time: a revocation anywhere is seen at once."""
    if not token:
        raise Unauthorized("missing API key: send 'Authorization: Bearer <key>'")
    row = session.execute(
        select(ApiKey.id, ApiKey.name, ApiKey.scopes, ApiKey.environment_ids).where(
            ApiKey.key_hash == hash_key(token), ApiKey.revoked_at.is_(None)
        )
    ).one_or_none()
    if row is None:
        raise Unauthorized("unknown or revoked API key")
    envs = None if row.environment_ids is None else tuple(row.environment_ids)
    principal = Principal(row.id, row.name, tuple(row.scopes), envs)
    if needed is not None:
        require_scope(principal, needed)
    return principal


def require_scope(principal: Principal, needed: Scope) -> Principal:
    """``principal`` when it holds scope ``needed``; 403 otherwise."""
    if principal.holds(needed):
        return principal
    if needed in effective_scopes(principal.scopes):
        raise Forbidden(f"this key is limited to environments; '{needed}' covers every environment")
    raise Forbidden(f"this key's scopes {list(principal.scopes)} do not include '{needed}'")


def can_reach(principal: Principal, environment_id: str) -> bool:
    """Whether the caller may see or act on environment ``environment_id``."""
    return principal.environment_ids is None or environment_id in principal.environment_ids


def require_environment(
    principal: Principal, environment_id: str, *, detail: str | None = None
) -> None:
    """404 unless the caller reaches ``environment_id``. ``detail`` is the answer the route
    gives for an id that does not exist ("snapshot <id> not found"), so both are word for
    word the same: a key limited to environments learns nothing about the others."""
    if not can_reach(principal, environment_id):
        raise NotFound(detail or f"environment {environment_id} not found")


def require_job_control(principal: Principal, job_id: str, environment_id: str | None) -> None:
    """Who may cancel a job: an admin key, or a key that reaches the job's environment (404
    otherwise, as for reads). A job of no environment (a library object's) needs admin."""
    if principal.holds(Scope.admin):
        return
    if environment_id is None:
        raise Forbidden(f"job {job_id} belongs to no environment: cancelling it needs 'admin'")
    require_environment(principal, environment_id, detail=f"job {job_id} not found")


def revoke(session: Session, row: ApiKey) -> None:
    """Revoke a key; every API process refuses it from its next request. 409 LastAdminKey
    for the last admin key not revoked, so the service cannot lock its admins out."""
    if row.revoked_at is not None:
        return
    if Scope.admin in row.scopes:
        # FOR UPDATE (PostgreSQL): two admins revoking each other at once are serialised
        # and the second sees the first's revocation.
        active = session.scalars(
            select(ApiKey).where(ApiKey.revoked_at.is_(None)).with_for_update()
        ).all()
        if all(k.id == row.id for k in active if Scope.admin in k.scopes):
            raise Conflict(
                "this is the last admin key: create another admin key before revoking it",
                code="LastAdminKey",
            )
    row.revoked_at = utcnow()
    session.flush()


def bootstrap_admin_key(session: Session, token: str) -> bool:
    """Create the admin key ``token`` when no key exists yet; returns whether it did."""
    if session.scalar(select(ApiKey.id).limit(1)) is not None:
        return False
    create_key(session, "bootstrap admin", [Scope.admin], token=token)
    return True


class FailedKeyLimiter:
    """Unknown or revoked keys by client address, in a sliding window.

    After ``limit`` failures within ``window_s``, :meth:`check` raises 429 with the seconds
    until the oldest of them leaves the window. Blocked requests are not looked up and do
    not count, so a guesser gets at most ``limit`` tries per window. Per process; at most
    ``max_clients`` addresses are tracked (the least recently failing are forgotten)."""

    def __init__(
        self, max_clients: int = 10_000, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.max_clients = max_clients
        self._clock = clock
        self._failures: OrderedDict[str, deque[float]] = OrderedDict()
        self._lock = threading.Lock()

    def check(self, client: str, *, limit: int, window_s: float) -> None:
        with self._lock:
            times = self._failures.get(client)
            if times is None:
                return
            now = self._clock()
            while times and times[0] <= now - window_s:
                times.popleft()
            if not times:
                del self._failures[client]
                return
            if len(times) >= limit:
                wait = times[len(times) - limit] + window_s - now
                raise TooManyRequests(
                    f"too many unknown or revoked API keys from {client}; try again later",
                    retry_after_s=max(1, math.ceil(wait)),
                )

    def record_failure(self, client: str, *, limit: int, window_s: float) -> None:
        with self._lock:
            now = self._clock()
            # only the newest ``limit`` failures matter: memory per address is bounded
            times = deque(self._failures.pop(client, ()), maxlen=limit)
            while times and times[0] <= now - window_s:
                times.popleft()
            times.append(now)
            self._failures[client] = times  # most recent last
            while len(self._failures) > self.max_clients:
                self._failures.popitem(last=False)

    def tracked(self) -> int:
        return len(self._failures)
