"""Standard Webhooks signatures: the sender's headers and the receiver's check.

``webhook-id`` (the event id, the same on every retry), ``webhook-timestamp`` (unix seconds of
the attempt) and ``webhook-signature: v1,<base64 HMAC-SHA256 of "{id}.{timestamp}.{body}">``
keyed with the base64-decoded secret after its ``whsec_`` prefix; during a rotation's overlap
one signature per valid secret, space-separated.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import secrets
import time
from collections.abc import Mapping, Sequence

SECRET_PREFIX = "whsec_"
SECRET_BYTES = 32


class WebhookVerificationError(ValueError):
    """A webhook whose signature, timestamp or headers do not check out."""


def new_secret() -> str:
    """A Standard Webhooks secret: ``whsec_`` and the base64 of 32 random bytes."""
    return SECRET_PREFIX + base64.b64encode(secrets.token_bytes(SECRET_BYTES)).decode()


def _secret_key(secret: str) -> bytes:
    raw = secret.removeprefix(SECRET_PREFIX)
    try:
        return base64.b64decode(raw, validate=True)
    except ValueError as exc:
        raise WebhookVerificationError("the secret is not whsec_<base64>") from exc


def sign(secret: str, msg_id: str, timestamp: int, body: bytes) -> str:
    """The ``webhook-signature`` value: ``v1,<base64 HMAC-SHA256 of id.timestamp.body>``."""
    to_sign = f"{msg_id}.{timestamp}.".encode() + body
    digest = hmac.new(_secret_key(secret), to_sign, hashlib.sha256).digest()
    return "v1," + base64.b64encode(digest).decode()


def signed_headers(
    secret: str | Sequence[str], msg_id: str, body: bytes, timestamp: int
) -> dict[str, str]:
    """The three Standard Webhooks headers for one attempt. With several secrets (newest
    first: during a rotation's overlap) ``webhook-signature`` carries one signature per
    secret, space-separated, so a receiver holding either one can verify."""
    keys = [secret] if isinstance(secret, str) else list(secret)
    return {
        "webhook-id": msg_id,
        "webhook-timestamp": str(timestamp),
        "webhook-signature": " ".join(sign(k, msg_id, timestamp, body) for k in keys),
    }


def verify_signature(
    secret: str | Sequence[str],
    headers: Mapping[str, str],
    body: bytes,
    tolerance_s: float = 300,
    *,
    now: float | None = None,
) -> None:
    """Check a received webhook; raise :class:`WebhookVerificationError` unless one of the
    ``v1`` signatures matches and the timestamp is within ``tolerance_s`` of ``now``.

    ``secret`` may be several (a receiver that holds the new and the old secret while it
    switches after a rotation): a signature made with any of them is accepted. ``headers``
    may use any letter case; ``body`` must be the raw bytes as received."""
    lower = {k.lower(): v for k, v in headers.items()}
    msg_id = lower.get("webhook-id")
    stamp = lower.get("webhook-timestamp")
    signatures = lower.get("webhook-signature")
    if not msg_id or not stamp or not signatures:
        raise WebhookVerificationError("missing webhook-id, webhook-timestamp or signature")
    if not (stamp.isascii() and stamp.isdigit() and len(stamp) <= 12):
        raise WebhookVerificationError("webhook-timestamp is not unix seconds (1-12 digits)")
    timestamp = int(stamp)
    current = time.time() if now is None else now
    if abs(current - timestamp) > tolerance_s:
        raise WebhookVerificationError("webhook-timestamp is outside the tolerance")
    keys = [secret] if isinstance(secret, str) else list(secret)
    expected = [sign(k, msg_id, timestamp, body).removeprefix("v1,").encode() for k in keys]
    for candidate in signatures.split():
        version, _, value = candidate.partition(",")
        if version == "v1" and any(hmac.compare_digest(value.encode(), e) for e in expected):
            return
    raise WebhookVerificationError("no matching signature")
