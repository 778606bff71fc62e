"""From an event to deliveries: one pending delivery per matching active subscription, in the
transaction of the state change, each sent by a ``webhooks.deliver`` task after commit.

Deliveries of one subscription and one environment share an ordering key and are sent one at a
time, oldest first (``seq``, then id). A platform adapter subscription gets one delivery per
changed twin instance, its body rendered here (the twin's records are in this transaction)."""

from __future__ import annotations

from typing import Any

from sqlalchemy import func, or_, select
from sqlalchemy.orm import Session

from app.core import queue
from app.core.enums import DeliveryState
from app.core.models import Delivery, Event, WebhookSubscription, utcnow
from app.core.webhooks.adapters import InstanceChange, WebhookFormat, instance_changes, render

DELIVER_TASK = "webhooks.deliver"
DISPATCH_TASK = "webhooks.dispatch"


def ordering_key(subscription_id: str, environment_id: str | None) -> str:
    return f"{subscription_id}:{environment_id or '-'}"


def fan_out(session: Session, event: Event) -> int:
    """Create the pending deliveries of ``event`` for every active subscription matching it
    (its type, and its environment when the subscription has a filter); each is sent after
    commit. A CloudEvents subscription gets one delivery; a platform adapter subscription
    one per instance the event changed (:mod:`.adapters`), in the order the twin applied
    them, all on the subscription's ordering key. Returns how many."""
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
    changes: list[InstanceChange] | None = None
    count = 0
    for sub in subs:
        if str(event.type) not in sub.event_types:
            continue
        fmt = WebhookFormat(sub.format)
        if fmt == WebhookFormat.cloudevents:
            _add(session, sub, event, None, None, None)
            count += 1
            continue
        if changes is None:
            changes = instance_changes(session, event)
        for change in changes:
            _add(session, sub, event, change.instance_id, render(fmt, change), change.twin_id)
            count += 1
    return count


def _add(
    session: Session,
    sub: WebhookSubscription,
    event: Event,
    instance_id: str | None,
    payload: Any,
    twin_id: str | None,
) -> None:
    key = ordering_key(sub.id, event.environment_id)
    last = session.scalar(select(func.max(Delivery.seq)).where(Delivery.ordering_key == key))
    now = utcnow()
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
        instance_id=instance_id,
        twin_id=twin_id,
        payload=payload,
    )
    session.add(delivery)
    session.flush()
    queue.enqueue(session, DELIVER_TASK, delivery_id=delivery.id)
