"""API keys: random tokens shown once, stored as SHA-256 hashes, with scopes.

Scopes: ``capture`` uploads snapshots, ``read`` reads everything, ``admin`` manages objects,
environments, webhooks and keys and implies the other two.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.core.enums import Scope
from app.core.errors import Forbidden, InvalidInput, Unauthorized
from app.core.models import ApiKey

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


def authenticate(session: Session, token: str | None, needed: Scope) -> ApiKey:
    """The live key for ``token`` with scope ``needed``; 401 when missing or wrong, 403 when
    the key lacks the scope."""
    if not token:
        raise Unauthorized("missing API key: send 'Authorization: Bearer <key>'")
    digest = hash_key(token)
    row = session.scalar(select(ApiKey).where(ApiKey.key_hash == digest))
    if row is None or row.revoked_at is not None or not hmac.compare_digest(row.key_hash, digest):
        raise Unauthorized("unknown or revoked API key")
    if needed not in effective_scopes(row.scopes):
        raise Forbidden(f"this key's scopes {row.scopes} do not include '{needed}'")
    return row


def bootstrap_admin_key(session: Session, token: str) -> bool:
    """Create the admin key ``token`` when no key exists yet; returns whether it did."""
    if session.scalar(select(ApiKey.id).limit(1)) is not None:
        return False
    create_key(session, "bootstrap admin", [Scope.admin], token=token)
    return True
