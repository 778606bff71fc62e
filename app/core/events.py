"""Events for the twin platform, recorded as rows in the same transaction as the state
change that causes them; :mod:`app.core.webhooks` fans them out to subscriptions."""

from __future__ import annotations

from typing import Any

from sqlalchemy.orm import Session

from app.core import webhooks
from app.core.enums import EventType
from app.core.models import Event


def record(
    session: Session,
    event_type: EventType,
    *,
    environment_id: str | None,
    subject: str | None,
    data: dict[str, Any],
) -> Event:
    """Insert the event and one pending delivery per matching subscription; deliveries are
    sent after commit."""
    event = Event(type=event_type, environment_id=environment_id, subject=subject, data=data)
    session.add(event)
    session.flush()
    webhooks.fan_out(session, event)
    return event
