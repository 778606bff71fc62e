"""The worker's side of one delivery: :func:`claim` (short transaction) → :func:`send` (no
session open) → :func:`record_attempt` (short transaction).

Only the head of an ordering key (its oldest pending delivery) may be claimed; the claim takes
a lease (``locked_until``) with a conditional UPDATE guarded by the attempt counter, which is
also the fencing token :func:`record_attempt` checks. A failed attempt schedules the next one
from ``Settings.webhook_retry_schedule_s`` (±20 % jitter) in the database; no thread sleeps.
"""

from __future__ import annotations

import json
import logging
import random
import threading
import time
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from typing import Any

import httpcore
from sqlalchemy import Select, exists, or_, select, update
from sqlalchemy.orm import Session, aliased

from app.core import queue, secretbox
from app.core.enums import DeliveryState
from app.core.models import Delivery, DeliveryAttempt, Event, WebhookSubscription, utcnow
from app.core.settings import Settings
from app.core.webhooks.adapters import CONTENT_TYPES, WebhookFormat, message_id, target_headers
from app.core.webhooks.fanout import DELIVER_TASK
from app.core.webhooks.payload import cloudevent
from app.core.webhooks.signing import signed_headers
from app.core.webhooks.subscriptions import signing_secrets
from app.core.webhooks.targets import allowed_networks
from app.core.webhooks.transport import (
    Deadline,
    PinnedBackend,
    Refused,
    resolve_within,
    tls_context,
)

log = logging.getLogger(__name__)
EXCERPT_BYTES = 1024
JITTER = 0.2
USER_AGENT = "twindelta-webhooks/1"
# A claim's lease outlasts the attempt's deadline by this much (the watchdog's grace, the
# claim and record transactions); an attempt that could not finish inside it is not started.
LEASE_MARGIN_S = 30.0
ABORT_GRACE_S = 0.5


@dataclass(frozen=True)
class Claim:
    """What one attempt needs, detached from the session: the HTTP call holds no session."""

    delivery_id: str
    attempt: int
    run_attempt: int
    url: str
    secrets: tuple[str, ...] = field(repr=False)  # the signing secrets, newest first
    message_id: str  # webhook-id: the event id (and instance, for an adapter body)
    body: bytes
    lease_until: datetime
    content_type: str = CONTENT_TYPES[WebhookFormat.cloudevents]
    headers: tuple[tuple[str, str], ...] = ()  # more headers of the format (adapters)


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
            Delivery.instance_id,
            Delivery.payload,
            Delivery.twin_id,
        )
        .execution_options(synchronize_session=False)
    ).first()
    return None if row is None else _prepare(session, settings, tuple(row), now)


def _prepare(
    session: Session, settings: Settings, row: tuple[Any, ...], now: datetime
) -> Claim | None:
    """The claimed attempt's request (None, and the delivery failed, when its subscription
    is gone or deactivated)."""
    claimed_id, attempt, run_attempt, subscription_id, event_id, instance_id, payload, twin_id = row
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
    try:
        keys = signing_secrets(settings, sub, now)
    except secretbox.SecretUnreadable as exc:  # the attempt is logged as failed, not lost
        log.error("delivery %s: %s", claimed_id, exc.detail)
        keys = ()
    headers: tuple[tuple[str, str], ...] = ()
    if instance_id is None:  # one CloudEvent per event
        fmt, doc = WebhookFormat.cloudevents, cloudevent(event)
    else:  # an adapter body, rendered at fan-out
        fmt, doc = WebhookFormat(sub.format), payload
        headers = tuple(target_headers(fmt, event, instance_id, twin_id).items())
    return Claim(
        delivery_id=claimed_id,
        attempt=attempt,
        run_attempt=run_attempt,
        url=sub.url,
        secrets=keys,
        message_id=message_id(event.id, instance_id),
        body=json.dumps(doc, separators=(",", ":"), ensure_ascii=False).encode(),
        lease_until=now + timedelta(seconds=lease_s(settings)),
        content_type=CONTENT_TYPES[fmt],
        headers=headers,
    )


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
    deadline = Deadline(time.monotonic() + budget)
    backend: PinnedBackend | None = None
    watchdog: threading.Timer | None = None
    try:
        if not claim.secrets:
            raise Refused("the signing secret cannot be decrypted (TWINDELTA_SECRET_KEY)")
        target = resolve_within(claim.url, allowed_networks(settings), deadline)
        headers = dict(claim.headers)
        stamp = int(time.time())
        headers.update(signed_headers(claim.secrets, claim.message_id, claim.body, stamp))
        headers.update({"content-type": claim.content_type, "user-agent": USER_AGENT})
        backend = PinnedBackend(target.addresses, deadline)
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
    except Refused as exc:
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
