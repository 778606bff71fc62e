"""A subscription's delivery log (each delivery with its event and every attempt) and
redelivery on request."""

from __future__ import annotations

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.core import queue
from app.core.enums import DeliveryState
from app.core.errors import Conflict, NotFound
from app.core.models import Delivery, DeliveryAttempt, Event, utcnow
from app.core.webhooks.fanout import DELIVER_TASK
from app.core.webhooks.payload import aware
from app.core.webhooks.subscriptions import get_subscription


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
    if delivery.locked_until is not None and aware(delivery.locked_until) > now:
        raise Conflict(f"an attempt of delivery {delivery.id} is in flight", code="InFlight")
    delivery.state = DeliveryState.pending
    delivery.run_attempts = 0
    delivery.next_attempt_at = now
    delivery.dispatched_at = now
    delivery.finished_at = None
    session.flush()
    queue.enqueue(session, DELIVER_TASK, delivery_id=delivery.id)
    return delivery
