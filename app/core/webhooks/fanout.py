"""From an event to deliveries: one pending delivery per matching active subscription, in the
transaction of the state change, each sent by a ``webhooks.deliver`` task after commit.

Deliveries of one subscription and one environment share an ordering key and are sent one at a
time, oldest first (``seq``, then id)."""

from __future__ import annotations

from sqlalchemy import func, or_, select
from sqlalchemy.orm import Session

from app.core import queue
from app.core.enums import DeliveryState
from app.core.models import Delivery, Event, WebhookSubscription, utcnow

DELIVER_TASK = "webhooks.deliver"
DISPATCH_TASK = "webhooks.dispatch"


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
