"""The dispatcher (beat's ``webhooks.dispatch``): a deliver message for every due head of an
ordering key that has none on its way, so a worker that dies mid-schedule loses nothing."""

from __future__ import annotations

from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import and_, exists, or_, select, update
from sqlalchemy.orm import Session, aliased

from app.core import queue
from app.core.enums import DeliveryState
from app.core.models import Delivery, utcnow
from app.core.webhooks.fanout import DELIVER_TASK

# A deliver message that has not led to a claim after this long is taken as lost and sent
# again by the dispatcher (duplicates are harmless: the claim is conditional).
REDISPATCH_AFTER_S = 60.0


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
