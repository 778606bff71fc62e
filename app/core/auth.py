"""API keys: random tokens shown once, stored as SHA-256 hashes, with scopes.

Scopes: ``capture`` uploads snapshots, ``read`` reads everything, ``admin`` manages objects,
environments, webhooks and keys and implies the other two.
"""

from __future__ import annotations

import hashlib
import secrets
import threading
import time
from dataclasses import dataclass

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.core.enums import Scope
from app.core.errors import Forbidden, InvalidInput, Unauthorized
from app.core.models import ApiKey, utcnow

KEY_PREFIX = "td_"
IMPLIED_SCOPES: dict[Scope, set[Scope]] = {
    Scope.admin: {Scope.admin, Scope.read, Scope.capture},
    Scope.read: {Scope.read},
    Scope.capture: {Scope.capture},
}


def hash_key(token: str) -> str:
    """Hex SHA-256 of a token. Tokens carry 256 random bits, so no salt or stretching is
    needed; a lookup by hash is constant-time with respect to the secret."""
    return hashlib.sha256(token.encode()).hexdigest()


def effective_scopes(scopes: list[str]) -> set[Scope]:
    out: set[Scope] = set()
    for name in scopes:
        out |= IMPLIED_SCOPES[Scope(name)]
    return out


def create_key(
    session: Session, name: str, scopes: list[str], token: str | None = None
) -> tuple[ApiKey, str]:
    """Create a key; returns the row and the plain token (shown once, never stored)."""
    try:
        parsed = sorted({Scope(s) for s in scopes})
    except ValueError as exc:
        raise InvalidInput(f"unknown scope in {scopes}; use capture, read or admin") from exc
    if not parsed:
        raise InvalidInput("a key needs at least one scope")
    token = token or KEY_PREFIX + secrets.token_urlsafe(32)
    row = ApiKey(name=name, prefix=token[:10], key_hash=hash_key(token), scopes=list(parsed))
    session.add(row)
    session.flush()
    return row, token


@dataclass(frozen=True)
class Principal:
    """Who is calling: the key's id, name and scopes (no secret)."""

    key_id: str
    name: str
    scopes: tuple[str, ...]


class _KeyCache:
    """Valid keys by hash for ``ttl_s`` seconds, so polling does not cost a query per
    request. A revocation made in this process clears it at once; other processes see it
    within ``ttl_s``. Unknown keys are never cached."""

    def __init__(self, ttl_s: float) -> None:
        self.ttl_s = ttl_s
        self._entries: dict[str, tuple[float, Principal]] = {}
        self._lock = threading.Lock()

    def get(self, digest: str) -> Principal | None:
        entry = self._entries.get(digest)
        if entry is None or entry[0] < time.monotonic():
            return None
        return entry[1]

    def put(self, digest: str, principal: Principal) -> None:
        with self._lock:
            if len(self._entries) > 10_000:
                self._entries.clear()
            self._entries[digest] = (time.monotonic() + self.ttl_s, principal)

    def clear(self) -> None:
        with self._lock:
            self._entries.clear()


KEY_CACHE = _KeyCache(ttl_s=5.0)


def cached(token: str | None, needed: Scope) -> Principal | None:
    """The caller from the cache when the key is cached and holds ``needed``; None when the
    database must be asked (which also raises the right 401/403)."""
    if not token:
        return None
    principal = KEY_CACHE.get(hash_key(token))
    if principal is None or needed not in effective_scopes(list(principal.scopes)):
        return None
    return principal


def authenticate(session: Session, token: str | None, needed: Scope) -> Principal:
    """The caller for ``token`` if it holds scope ``needed``; 401 when the key is missing,
    unknown or revoked, 403 when it lacks the scope."""
    if not token:
        raise Unauthorized("missing API key: send 'Authorization: Bearer <key>'")
    digest = hash_key(token)
    principal = KEY_CACHE.get(digest)
    if principal is None:
        row = session.scalar(select(ApiKey).where(ApiKey.key_hash == digest))
        if row is None or row.revoked_at is not None:
            raise Unauthorized("unknown or revoked API key")
        principal = Principal(row.id, row.name, tuple(row.scopes))
        KEY_CACHE.put(digest, principal)
    if needed not in effective_scopes(list(principal.scopes)):
        raise Forbidden(f"this key's scopes {list(principal.scopes)} do not include '{needed}'")
    return principal


def revoke(row: ApiKey) -> None:
    """Revoke a key; effective at once in this process, within the cache TTL elsewhere."""
    row.revoked_at = row.revoked_at or utcnow()
    KEY_CACHE.clear()


def bootstrap_admin_key(session: Session, token: str) -> bool:
    """Create the admin key ``token`` when no key exists yet; returns whether it did."""
    if session.scalar(select(ApiKey.id).limit(1)) is not None:
        return False
    create_key(session, "bootstrap admin", [Scope.admin], token=token)
    return True
