"""Webhook subscriptions and deliveries: rows first, HTTP second.

An event is recorded in the transaction of the state change that causes it
(:func:`app.core.events.record`); :func:`fan_out` adds one pending delivery per matching
active subscription in that same transaction and enqueues ``webhooks.deliver`` after commit.

Ordering. Deliveries of one subscription and one environment share an ``ordering_key`` and
are sent one at a time, oldest first (``seq``, then id): only the *head* (the oldest pending
delivery of its key) may be claimed, so a later event waits while an earlier one is retrying.
Different keys never wait for each other: each delivery is its own task.

Scheduling lives in the database. A failed attempt sets ``next_attempt_at`` from
``Settings.webhook_retry_schedule_s`` (with ±20 % jitter) and releases the delivery; the
``webhooks.dispatch`` beat task sends a deliver message for every head that has come due
(and re-sends one whose message seems lost). No worker thread sleeps, and a worker that dies
mid-schedule loses nothing: the next dispatcher tick finds the row.

Claiming. :func:`claim` takes a lease (``locked_until``) with a conditional UPDATE guarded by
the attempt counter, so two workers never send the same attempt; the counter is also the
fencing token that :func:`record_attempt` checks before it changes the delivery.

A deliver task is: ``claim`` (short transaction) → :func:`send` (no session open) →
``record_attempt`` (short transaction).

Hostile receivers and networks. :func:`send` gives each attempt one overall deadline
(``Settings.webhook_timeout_s``: lookup, connect, TLS, request, response headers and excerpt),
so a receiver that trickles one byte at a time cannot hold a worker thread past it; the lease
is that deadline plus :data:`LEASE_MARGIN_S` and an attempt never runs into the margin, so a
lease never expires under a live attempt. The host is resolved once per attempt, every address
checked again (DNS can change since the subscription was made), and the connection goes to a
checked address: no second lookup that a rebinding DNS server could answer differently, and no
proxy from the environment. TLS verifies the certificate against the URL's host name.

Signatures follow Standard Webhooks: ``webhook-id`` (the event id, the same on every retry),
``webhook-timestamp`` (unix seconds of the attempt) and ``webhook-signature:
v1,<base64 HMAC-SHA256 of "{id}.{timestamp}.{body}">`` keyed with the base64-decoded secret
after its ``whsec_`` prefix. After :func:`rotate_secret` the header carries one signature per
valid secret, ``v1,<new> v1,<previous>``, until the overlap ends. :func:`verify_signature` is
the receiver's side. Secrets are stored encrypted (:mod:`app.core.secretbox`).
"""

from __future__ import annotations

import base64
import contextlib
import hashlib
import hmac
import ipaddress
import json
import logging
import random
import secrets
import socket
import ssl
import threading
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from functools import lru_cache
from typing import Any
from urllib.parse import urlsplit

import httpcore
import httpx
from sqlalchemy import Select, and_, exists, func, or_, select, update
from sqlalchemy.orm import Session, aliased

from app.core import queue, secretbox
from app.core.enums import DeliveryState, EventType
from app.core.errors import Conflict, InvalidInput, NotFound
from app.core.models import (
    Delivery,
    DeliveryAttempt,
    Environment,
    Event,
    WebhookSubscription,
    utcnow,
)
from app.core.settings import Settings

log = logging.getLogger(__name__)

DELIVER_TASK = "webhooks.deliver"
DISPATCH_TASK = "webhooks.dispatch"
SECRET_PREFIX = "whsec_"
SECRET_BYTES = 32
EXCERPT_BYTES = 1024
JITTER = 0.2
USER_AGENT = "twindelta-webhooks/1"
CONTENT_TYPE = "application/cloudevents+json; charset=utf-8"
# A deliver message that has not led to a claim after this long is taken as lost and sent
# again by the dispatcher (duplicates are harmless: the claim is conditional).
REDISPATCH_AFTER_S = 60.0
# A claim's lease outlasts the attempt's deadline by this much (the watchdog's grace, the
# claim and record transactions); an attempt that could not finish inside it is not started.
LEASE_MARGIN_S = 30.0
ABORT_GRACE_S = 0.5
IpAddress = ipaddress.IPv4Address | ipaddress.IPv6Address
Network = ipaddress.IPv4Network | ipaddress.IPv6Network


# --- signatures -----------------------------------------------------------------------------


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


# --- target addresses -----------------------------------------------------------------------


def allowed_networks(settings: Settings) -> list[Network]:
    """``Settings.webhook_allowed_networks`` parsed (CIDRs of private targets allowed)."""
    try:
        return [ipaddress.ip_network(n, strict=False) for n in settings.webhook_allowed_networks]
    except ValueError as exc:
        raise InvalidInput(f"TWINDELTA_WEBHOOK_ALLOWED_NETWORKS: {exc}") from exc


def _is_public(ip: IpAddress) -> bool:
    if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
        ip = ip.ipv4_mapped
    return ip.is_global and not ip.is_multicast


def _resolve(host: str, port: int) -> list[IpAddress]:
    try:
        return [ipaddress.ip_address(host)]
    except ValueError:
        pass
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except OSError as exc:
        raise InvalidInput(f"url: cannot resolve host {host!r} ({exc})") from exc
    return [ipaddress.ip_address(str(info[4][0]).split("%", 1)[0]) for info in infos]


@dataclass(frozen=True)
class Target:
    """A webhook URL's host resolved once, every address checked: the only addresses an
    attempt may connect to (a second lookup could answer differently: DNS rebinding)."""

    host: str
    port: int
    addresses: tuple[IpAddress, ...]


def resolve_target(url: str, networks: Sequence[Network]) -> Target:
    """Resolve ``url``'s host once and check every address it has; refuse (InvalidInput,
    422) a URL that is not http(s), or whose host is or resolves to a non-public address
    (loopback, RFC 1918, link-local, unique-local, ...) outside ``networks``."""
    try:
        parts = urlsplit(url)
        port = parts.port or (443 if parts.scheme == "https" else 80)
    except ValueError as exc:
        raise InvalidInput(f"url: {exc}") from exc
    if parts.scheme not in {"http", "https"}:
        raise InvalidInput("url: only http and https URLs can receive webhooks")
    if not parts.hostname:
        raise InvalidInput("url: the URL has no host")
    addresses = _resolve(parts.hostname, port)
    for ip in addresses:
        if _is_public(ip) or any(ip in net for net in networks):
            continue
        raise InvalidInput(
            f"url: {parts.hostname} is the non-public address {ip}; private targets need "
            "TWINDELTA_WEBHOOK_ALLOWED_NETWORKS",
            code="WebhookTargetRefused",
        )
    if not addresses:
        raise InvalidInput(f"url: host {parts.hostname!r} has no address")
    return Target(parts.hostname, port, tuple(dict.fromkeys(addresses)))


def check_target(url: str, networks: Sequence[Network]) -> None:
    """:func:`resolve_target` for its refusals only (when a subscription is made)."""
    resolve_target(url, networks)


# --- subscriptions --------------------------------------------------------------------------


def create_subscription(
    session: Session,
    settings: Settings,
    *,
    url: str,
    event_types: Iterable[EventType] | None,
    environment_id: str | None,
) -> WebhookSubscription:
    """A new active subscription with a fresh secret (the caller shows it once)."""
    check_target(url, allowed_networks(settings))
    types = sorted({EventType(t) for t in event_types} if event_types else set(EventType))
    if environment_id is not None and session.get(Environment, environment_id) is None:
        raise InvalidInput(f"environment_id: environment {environment_id} not found")
    sub = WebhookSubscription(
        url=url,
        event_types=[str(t) for t in types],
        environment_id=environment_id,
        secret_encrypted=secretbox.encrypt(settings, new_secret()),
        active=True,
    )
    session.add(sub)
    session.flush()
    return sub


def current_secret(settings: Settings, sub: WebhookSubscription) -> str:
    """The subscription's signing secret in plain text (stored encrypted)."""
    return secretbox.decrypt(settings, sub.secret_encrypted)


def signing_secrets(
    settings: Settings, sub: WebhookSubscription, now: datetime | None = None
) -> tuple[str, ...]:
    """The secrets a delivery is signed with now: the current one, and the previous one while
    a rotation's overlap lasts (Standard Webhooks: one signature each, space-separated)."""
    now = now or utcnow()
    out = [current_secret(settings, sub)]
    expires = sub.previous_secret_expires_at
    if sub.previous_secret_encrypted and expires is not None and _aware(expires) > now:
        out.append(secretbox.decrypt(settings, sub.previous_secret_encrypted))
    return tuple(out)


def reencrypt_secrets(session: Session, settings: Settings) -> int:
    """Re-encrypt every stored signing secret under the newest TWINDELTA_SECRET_KEY (after
    the key was changed to "new,old"); then the old key can be dropped. Returns how many."""
    count = 0
    for sub in session.scalars(select(WebhookSubscription)):
        sub.secret_encrypted = secretbox.reencrypt(settings, sub.secret_encrypted)
        if sub.previous_secret_encrypted:
            sub.previous_secret_encrypted = secretbox.reencrypt(
                settings, sub.previous_secret_encrypted
            )
        count += 1
    session.flush()
    return count


def rotate_secret(
    session: Session, settings: Settings, subscription_id: str, now: datetime | None = None
) -> tuple[WebhookSubscription, str]:
    """Give a subscription a new secret; returns it in plain text (the caller shows it once).

    The current secret becomes the previous one and keeps signing, next to the new one, for
    ``Settings.webhook_secret_overlap_s``; a previous secret from an earlier rotation is
    dropped. 409 for a deactivated subscription."""
    sub = get_subscription(session, subscription_id)
    if not sub.active:
        raise Conflict(f"webhook {sub.id} is deactivated", code="WebhookInactive")
    now = now or utcnow()
    secret = new_secret()
    overlap = settings.webhook_secret_overlap_s
    sub.previous_secret_encrypted = sub.secret_encrypted if overlap > 0 else None
    sub.previous_secret_expires_at = now + timedelta(seconds=overlap) if overlap > 0 else None
    sub.secret_encrypted = secretbox.encrypt(settings, secret)
    session.flush()
    return sub, secret


def get_subscription(session: Session, subscription_id: str) -> WebhookSubscription:
    sub = session.get(WebhookSubscription, subscription_id)
    if sub is None:
        raise NotFound(f"webhook {subscription_id} not found")
    return sub


def list_subscriptions(session: Session) -> Sequence[WebhookSubscription]:
    return session.scalars(
        select(WebhookSubscription).order_by(WebhookSubscription.created_at)
    ).all()


def deactivate(session: Session, subscription_id: str) -> WebhookSubscription:
    """Stop a subscription: no new deliveries, and its pending ones end as failed."""
    sub = get_subscription(session, subscription_id)
    now = utcnow()
    if sub.active:
        sub.active, sub.deactivated_at = False, now
    session.execute(
        update(Delivery)
        .where(Delivery.subscription_id == sub.id, Delivery.state == DeliveryState.pending)
        .values(state=DeliveryState.failed, finished_at=now, last_error="subscription deactivated")
    )
    session.flush()
    return sub


def list_deliveries(
    session: Session, subscription_id: str, *, state: DeliveryState | None, limit: int
) -> list[tuple[Delivery, Event, list[DeliveryAttempt]]]:
    """The delivery log of a subscription, newest first, each with every attempt."""
    get_subscription(session, subscription_id)
    query = select(Delivery, Event).join(Event, Event.id == Delivery.event_id)
    query = query.where(Delivery.subscription_id == subscription_id)
    if state is not None:
        query = query.where(Delivery.state == state)
    rows = session.execute(
        query.order_by(Delivery.created_at.desc(), Delivery.seq.desc()).limit(limit)
    ).all()
    attempts = _attempts_of(session, [d.id for d, _ in rows])
    return [(d, e, attempts[d.id]) for d, e in rows]


def describe(session: Session, delivery: Delivery) -> tuple[Delivery, Event, list[DeliveryAttempt]]:
    """A delivery with its event and every attempt, for the log."""
    event = session.get(Event, delivery.event_id)
    if event is None:
        raise NotFound(f"event {delivery.event_id} not found")
    return delivery, event, _attempts_of(session, [delivery.id])[delivery.id]


def _attempts_of(session: Session, ids: list[str]) -> dict[str, list[DeliveryAttempt]]:
    attempts: dict[str, list[DeliveryAttempt]] = {i: [] for i in ids}
    if ids:
        for a in session.scalars(
            select(DeliveryAttempt)
            .where(DeliveryAttempt.delivery_id.in_(ids))
            .order_by(DeliveryAttempt.number)
        ):
            attempts[a.delivery_id].append(a)
    return attempts


def get_delivery(session: Session, subscription_id: str, delivery_id: str) -> Delivery:
    delivery = session.get(Delivery, delivery_id)
    if delivery is None or delivery.subscription_id != subscription_id:
        raise NotFound(f"delivery {delivery_id} of webhook {subscription_id} not found")
    return delivery


def redeliver(session: Session, subscription_id: str, delivery_id: str) -> Delivery:
    """Start a new run of attempts for a delivery (also a failed or succeeded one); 409 while
    an attempt is in flight or the subscription is inactive."""
    sub = get_subscription(session, subscription_id)
    delivery = get_delivery(session, subscription_id, delivery_id)
    if not sub.active:
        raise Conflict(f"webhook {sub.id} is deactivated", code="WebhookInactive")
    now = utcnow()
    if delivery.locked_until is not None and _aware(delivery.locked_until) > now:
        raise Conflict(f"an attempt of delivery {delivery.id} is in flight", code="InFlight")
    delivery.state = DeliveryState.pending
    delivery.run_attempts = 0
    delivery.next_attempt_at = now
    delivery.dispatched_at = now
    delivery.finished_at = None
    session.flush()
    queue.enqueue(session, DELIVER_TASK, delivery_id=delivery.id)
    return delivery


# --- fan-out --------------------------------------------------------------------------------


def ordering_key(subscription_id: str, environment_id: str | None) -> str:
    return f"{subscription_id}:{environment_id or '-'}"


def fan_out(session: Session, event: Event) -> int:
    """Create a pending delivery per active subscription matching ``event`` (its type, and its
    environment when the subscription has a filter); each is sent after commit. Returns how
    many."""
    subs = session.scalars(
        select(WebhookSubscription)
        .where(
            WebhookSubscription.active.is_(True),
            or_(
                WebhookSubscription.environment_id.is_(None),
                WebhookSubscription.environment_id == event.environment_id,
            ),
        )
        .order_by(WebhookSubscription.created_at)
    ).all()
    now = utcnow()
    count = 0
    for sub in subs:
        if str(event.type) not in sub.event_types:
            continue
        key = ordering_key(sub.id, event.environment_id)
        last = session.scalar(select(func.max(Delivery.seq)).where(Delivery.ordering_key == key))
        delivery = Delivery(
            subscription_id=sub.id,
            event_id=event.id,
            ordering_key=key,
            seq=(last or 0) + 1,
            state=DeliveryState.pending,
            attempts=0,
            run_attempts=0,
            next_attempt_at=now,
            dispatched_at=now,
        )
        session.add(delivery)
        session.flush()
        queue.enqueue(session, DELIVER_TASK, delivery_id=delivery.id)
        count += 1
    return count


# --- the worker's side ----------------------------------------------------------------------


@dataclass(frozen=True)
class Claim:
    """What one attempt needs, detached from the session: the HTTP call holds no session."""

    delivery_id: str
    attempt: int
    run_attempt: int
    url: str
    secrets: tuple[str, ...] = field(repr=False)  # the signing secrets, newest first
    event_id: str
    body: bytes
    lease_until: datetime


@dataclass(frozen=True)
class Outcome:
    """The result of one HTTP attempt."""

    ok: bool
    status_code: int | None
    latency_ms: float | None
    response_excerpt: str | None
    error: str | None


def lease_s(settings: Settings) -> float:
    """How long a claim holds the delivery: the attempt's deadline (``webhook_timeout_s``)
    plus a margin for the watchdog, the claim and record transactions. :func:`send` never
    runs past the lease less that margin, so a lease never expires under a live attempt."""
    return settings.webhook_timeout_s + LEASE_MARGIN_S


def cloudevent(event: Event) -> dict[str, Any]:
    """The CloudEvents 1.0 structured form of an event; ``data`` is passed verbatim."""
    source = (
        f"/twindelta/environments/{event.environment_id}" if event.environment_id else "/twindelta"
    )
    body: dict[str, Any] = {
        "specversion": "1.0",
        "id": event.id,
        "source": source,
        "type": str(event.type),
        "time": _aware(event.created_at).isoformat().replace("+00:00", "Z"),
        "datacontenttype": "application/json",
        "data": event.data,
    }
    if event.subject is not None:
        body["subject"] = event.subject
    return body


def _head_query(key: str) -> Select[Delivery]:
    return (
        select(Delivery)
        .where(Delivery.ordering_key == key, Delivery.state == DeliveryState.pending)
        .order_by(Delivery.seq, Delivery.id)
        .limit(1)
    )


def claim(
    session: Session, delivery_id: str, settings: Settings, now: datetime | None = None
) -> Claim | None:
    """Claim the next attempt of ``delivery_id``'s ordering key: its head (the oldest pending
    delivery, which may be another one than asked for), when it is due, no attempt of the key
    is in flight and its subscription is active. None when there is nothing to do now.

    One conditional ``UPDATE ... RETURNING``: on PostgreSQL a concurrent claimer blocks on the
    row and then finds the lease taken; on SQLite the transaction starts with a write, so it
    waits for the write lock (busy timeout) instead of failing to upgrade a read."""
    now = now or utcnow()
    asked, head, busy = aliased(Delivery), aliased(Delivery), aliased(Delivery)
    key = select(asked.ordering_key).where(asked.id == delivery_id).scalar_subquery()
    head_id = (
        select(head.id)
        .where(head.ordering_key == key, head.state == DeliveryState.pending)
        .order_by(head.seq, head.id)
        .limit(1)
        .scalar_subquery()
    )
    in_flight = exists().where(
        busy.ordering_key == key, busy.state == DeliveryState.pending, busy.locked_until > now
    )
    row = session.execute(
        update(Delivery)
        .where(
            Delivery.id == head_id,
            Delivery.state == DeliveryState.pending,
            or_(Delivery.next_attempt_at.is_(None), Delivery.next_attempt_at <= now),
            or_(Delivery.locked_until.is_(None), Delivery.locked_until <= now),
            ~in_flight,
        )
        .values(
            attempts=Delivery.attempts + 1,
            run_attempts=Delivery.run_attempts + 1,
            locked_until=now + timedelta(seconds=lease_s(settings)),
            dispatched_at=None,  # the message is consumed; after the lease, send again
        )
        .returning(
            Delivery.id,
            Delivery.attempts,
            Delivery.run_attempts,
            Delivery.subscription_id,
            Delivery.event_id,
        )
        .execution_options(synchronize_session=False)
    ).first()
    if row is None:
        return None
    claimed_id, attempt, run_attempt, subscription_id, event_id = row
    sub = session.get(WebhookSubscription, subscription_id)
    event = session.get(Event, event_id)
    if sub is None or event is None or not sub.active:
        session.execute(
            update(Delivery)
            .where(Delivery.id == claimed_id)
            .values(
                state=DeliveryState.failed,
                finished_at=now,
                locked_until=None,
                last_error="subscription deactivated",
            )
            .execution_options(synchronize_session=False)
        )
        return None
    body = json.dumps(cloudevent(event), separators=(",", ":"), ensure_ascii=False).encode()
    lease_until = now + timedelta(seconds=lease_s(settings))
    try:
        keys = signing_secrets(settings, sub, now)
    except secretbox.SecretUnreadable as exc:  # the attempt is logged as failed, not lost
        log.error("delivery %s: %s", claimed_id, exc.detail)
        keys = ()
    return Claim(claimed_id, attempt, run_attempt, sub.url, keys, event.id, body, lease_until)


@lru_cache(maxsize=1)
def tls_context() -> ssl.SSLContext:
    """The verifying TLS context, built once per process (it costs ~50 ms): certifi's CAs,
    or the operator's from ``SSL_CERT_FILE`` / ``SSL_CERT_DIR`` (receivers behind a private
    CA). Certificates are verified against the URL's host name."""
    return httpx.create_ssl_context()


class _Deadline:
    """The monotonic instant by which one attempt ends, whatever the receiver does."""

    def __init__(self, at: float) -> None:
        self.at = at

    def left(self) -> float:
        return self.at - time.monotonic()

    def clip(self, timeout: float | None, error: type[Exception]) -> float:
        """``timeout`` cut to what is left; ``error`` once nothing is."""
        left = self.left()
        if left <= 0:
            raise error("the attempt's deadline passed")
        return left if timeout is None else min(timeout, left)


class _PinnedStream(httpcore.NetworkStream):
    """A connection whose every read, write and TLS handshake ends by the deadline."""

    def __init__(self, inner: httpcore.NetworkStream, backend: _PinnedBackend) -> None:
        self._inner, self._backend, self._deadline = inner, backend, backend.deadline

    def read(self, max_bytes: int, timeout: float | None = None) -> bytes:
        return self._inner.read(max_bytes, self._deadline.clip(timeout, httpcore.ReadTimeout))

    def write(self, buffer: bytes, timeout: float | None = None) -> None:
        self._inner.write(buffer, self._deadline.clip(timeout, httpcore.WriteTimeout))

    def close(self) -> None:
        self._inner.close()

    def start_tls(
        self,
        ssl_context: ssl.SSLContext,
        server_hostname: str | None = None,
        timeout: float | None = None,
    ) -> httpcore.NetworkStream:
        clipped = self._deadline.clip(timeout, httpcore.ConnectTimeout)
        tls = self._inner.start_tls(ssl_context, server_hostname, clipped)
        return self._backend.track(tls)

    def get_extra_info(self, info: str) -> Any:
        return self._inner.get_extra_info(info)


class _PinnedBackend(httpcore.NetworkBackend):
    """Connects only to the addresses that passed the check: the host name is never looked
    up again, so a DNS answer that changes after the check cannot send the attempt
    elsewhere. TLS still gets the URL's host name (httpcore passes it to ``start_tls``), so
    SNI and certificate verification are those of the name, and the Host header is the
    URL's. Every socket operation ends by the attempt's deadline, and :meth:`abort` shuts
    the sockets down (the watchdog's backstop for a TLS handshake that trickles in)."""

    def __init__(self, addresses: Sequence[IpAddress], deadline: _Deadline) -> None:
        self._addresses, self.deadline = list(addresses), deadline
        self._inner = httpcore.SyncBackend()
        self._streams: list[httpcore.NetworkStream] = []
        self._lock = threading.Lock()

    def connect_tcp(
        self,
        host: str,
        port: int,
        timeout: float | None = None,
        local_address: str | None = None,
        socket_options: Iterable[Any] | None = None,
    ) -> httpcore.NetworkStream:
        error: Exception = httpcore.ConnectError(f"{host} has no checked address")
        for ip in self._addresses:
            try:
                stream = self._inner.connect_tcp(
                    str(ip),
                    port,
                    timeout=self.deadline.clip(timeout, httpcore.ConnectTimeout),
                    local_address=local_address,
                    socket_options=socket_options,
                )
            except httpcore.ConnectError as exc:  # try the next address
                error = exc
                continue
            return self.track(stream)
        raise error

    def track(self, stream: httpcore.NetworkStream) -> _PinnedStream:
        """Wrap a new stream (TCP, or TLS over it: a new socket object) for :meth:`abort`."""
        with self._lock:
            self._streams.append(stream)
        return _PinnedStream(stream, self)

    def connect_unix_socket(
        self,
        path: str,
        timeout: float | None = None,
        socket_options: Iterable[Any] | None = None,
    ) -> httpcore.NetworkStream:
        raise httpcore.ConnectError("webhooks are not sent to unix sockets")

    def sleep(self, seconds: float) -> None:
        time.sleep(seconds)

    def abort(self) -> None:
        with self._lock:
            streams = list(self._streams)
        for stream in streams:
            with contextlib.suppress(AttributeError, OSError):  # closed, or detached by TLS
                stream.get_extra_info("socket").shutdown(socket.SHUT_RDWR)


class _Refused(Exception):
    pass


def _resolve_by(url: str, networks: Sequence[Network], deadline: _Deadline) -> Target:
    """:func:`resolve_target` within the deadline (``getaddrinfo`` has no timeout of its
    own: it runs in a helper thread that is left to finish on its own if it is late)."""
    result: list[Target | InvalidInput] = []
    done = threading.Event()

    def run() -> None:
        try:
            result.append(resolve_target(url, networks))
        except InvalidInput as exc:
            result.append(exc)
        finally:
            done.set()

    threading.Thread(target=run, name="webhook-resolve", daemon=True).start()
    if not done.wait(max(deadline.left(), 0.0)):
        raise httpcore.ConnectTimeout("resolving the host took past the deadline")
    if isinstance(result[0], InvalidInput):
        raise _Refused(result[0].detail)
    return result[0]


def attempt_budget_s(claim: Claim, settings: Settings) -> float:
    """Seconds one attempt may take: ``webhook_timeout_s``, and never past its lease less
    the margin (so no other worker can take the delivery while it is still sending)."""
    lease_left = (claim.lease_until - utcnow()).total_seconds() - LEASE_MARGIN_S
    return max(min(settings.webhook_timeout_s, lease_left), 0.0)


def send(claim: Claim, settings: Settings) -> Outcome:
    """POST the signed event; never raises. Any 2xx is success; redirects are not followed.

    One overall deadline (``webhook_timeout_s``) covers the lookup, connect, TLS, request,
    response headers and the 1 KB excerpt: a receiver that trickles bytes cannot hold the
    attempt past it. The host is resolved once and every address checked again (DNS can
    change since the subscription was made); the connection goes to a checked address, never
    through a proxy from the environment."""
    budget = attempt_budget_s(claim, settings)
    start = time.perf_counter()
    deadline = _Deadline(time.monotonic() + budget)
    backend: _PinnedBackend | None = None
    watchdog: threading.Timer | None = None
    try:
        if not claim.secrets:
            raise _Refused("the signing secret cannot be decrypted (TWINDELTA_SECRET_KEY)")
        target = _resolve_by(claim.url, allowed_networks(settings), deadline)
        headers = signed_headers(claim.secrets, claim.event_id, claim.body, int(time.time()))
        headers.update({"content-type": CONTENT_TYPE, "user-agent": USER_AGENT})
        backend = _PinnedBackend(target.addresses, deadline)
        watchdog = threading.Timer(max(deadline.left(), 0.0) + ABORT_GRACE_S, backend.abort)
        watchdog.daemon = True
        watchdog.start()
        extensions = {"timeout": dict.fromkeys(("connect", "read", "write", "pool"), budget)}
        request_headers = list(headers.items())
        with (
            httpcore.ConnectionPool(
                ssl_context=tls_context(), network_backend=backend, max_connections=1
            ) as pool,
            pool.stream(
                "POST",
                claim.url,
                headers=request_headers,
                content=claim.body,
                extensions=extensions,
            ) as response,
        ):
            latency = (time.perf_counter() - start) * 1000.0
            excerpt = bytearray()
            try:
                for chunk in response.iter_stream():
                    excerpt += chunk
                    if len(excerpt) >= EXCERPT_BYTES:
                        break
            except (httpcore.TimeoutException, httpcore.NetworkError):
                pass  # the status decides; the excerpt is what came by the deadline
            text = bytes(excerpt[:EXCERPT_BYTES]).decode("utf-8", errors="replace")
            ok = 200 <= response.status < 300
            error = None if ok else f"HTTP {response.status}"
            return Outcome(ok, response.status, latency, text, error)
    except _Refused as exc:
        return Outcome(False, None, None, None, f"refused: {exc}")
    except Exception as exc:  # a delivery must always be recorded
        if deadline.left() <= 0:
            error = f"deadline: no answer within {budget:g} s ({type(exc).__name__})"
        else:
            error = f"{type(exc).__name__}: {exc}"
    finally:
        if watchdog is not None:
            watchdog.cancel()
    return Outcome(False, None, (time.perf_counter() - start) * 1000.0, None, error[:2000])


def retry_delay_s(settings: Settings, run_attempt: int) -> float | None:
    """Seconds before the next attempt after failed attempt ``run_attempt`` of a run (±20 %
    jitter), or None when the schedule is used up."""
    schedule = settings.webhook_retry_schedule_s
    if run_attempt > len(schedule):
        return None
    return float(schedule[run_attempt - 1]) * random.uniform(1 - JITTER, 1 + JITTER)


def record_attempt(
    session: Session,
    claim: Claim,
    outcome: Outcome,
    settings: Settings,
    now: datetime | None = None,
) -> str:
    """Log the attempt and move the delivery on: succeeded, scheduled again, or failed (dead
    letter) when the schedule is used up. Only the attempt that holds the claim changes the
    delivery. When the delivery is final, the next one of its key is sent. Returns the new
    state, or ``"lost"`` when another attempt took the delivery over."""
    now = now or utcnow()
    session.add(
        DeliveryAttempt(
            delivery_id=claim.delivery_id,
            number=claim.attempt,
            attempted_at=now,
            status_code=outcome.status_code,
            latency_ms=outcome.latency_ms,
            response_excerpt=outcome.response_excerpt,
            error=outcome.error,
        )
    )
    values: dict[str, Any] = {
        "locked_until": None,
        "last_status_code": outcome.status_code,
        "last_error": outcome.error,
    }
    delay = None if outcome.ok else retry_delay_s(settings, claim.run_attempt)
    if outcome.ok:
        values.update(state=DeliveryState.succeeded, finished_at=now)
    elif delay is None:
        values.update(state=DeliveryState.failed, finished_at=now)
    else:
        values.update(next_attempt_at=now + timedelta(seconds=delay), dispatched_at=None)
    updated = session.execute(
        update(Delivery)
        .where(
            Delivery.id == claim.delivery_id,
            Delivery.state == DeliveryState.pending,
            Delivery.attempts == claim.attempt,
        )
        .values(**values)
        .execution_options(synchronize_session=False)
    )
    session.flush()
    if updated.rowcount != 1:  # type: ignore[attr-defined]
        log.warning("delivery %s attempt %s lost its claim", claim.delivery_id, claim.attempt)
        return "lost"
    if outcome.ok or delay is None:
        _send_next(session, claim.delivery_id, now)
        return str(values["state"])
    return "retrying"


def _send_next(session: Session, delivery_id: str, now: datetime) -> None:
    key = session.scalar(select(Delivery.ordering_key).where(Delivery.id == delivery_id))
    if key is None:
        return
    head = session.scalars(_head_query(key)).first()
    if head is not None:
        session.execute(
            update(Delivery)
            .where(Delivery.id == head.id)
            .values(dispatched_at=now)
            .execution_options(synchronize_session=False)
        )
        queue.enqueue(session, DELIVER_TASK, delivery_id=head.id)


def dispatch_due(session: Session, now: datetime | None = None, limit: int = 500) -> list[str]:
    """Send a deliver message for every due, unclaimed head of an ordering key that has no
    message on its way (or whose message seems lost); returns their ids. Run by beat.

    One ``UPDATE ... RETURNING`` marks them sent (a write first, for SQLite's sake)."""
    now = now or utcnow()
    head, older = aliased(Delivery), aliased(Delivery)
    stale = now - timedelta(seconds=REDISPATCH_AFTER_S)

    def not_sent(d: Any) -> Any:
        return or_(d.dispatched_at.is_(None), d.dispatched_at < stale)

    has_older = exists().where(
        older.ordering_key == head.ordering_key,
        older.state == DeliveryState.pending,
        or_(older.seq < head.seq, and_(older.seq == head.seq, older.id < head.id)),
    )
    due_heads = (
        select(head.id)
        .where(
            head.state == DeliveryState.pending,
            or_(head.next_attempt_at.is_(None), head.next_attempt_at <= now),
            or_(head.locked_until.is_(None), head.locked_until <= now),
            not_sent(head),
            ~has_older,
        )
        .order_by(head.next_attempt_at)
        .limit(limit)
    )
    sent = list(
        session.scalars(
            update(Delivery)
            .where(
                Delivery.id.in_(due_heads),
                Delivery.state == DeliveryState.pending,
                not_sent(Delivery),
            )
            .values(dispatched_at=now)
            .returning(Delivery.id)
            .execution_options(synchronize_session=False)
        )
    )
    for delivery_id in sent:
        queue.enqueue(session, DELIVER_TASK, delivery_id=delivery_id)
    return sent


def _aware(value: datetime) -> datetime:
    """SQLite returns naive datetimes; they are UTC."""
    return value if value.tzinfo else value.replace(tzinfo=UTC)
