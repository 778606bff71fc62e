"""Webhook subscriptions and deliveries (the delivery machinery comes with the webhooks
work; until then events are recorded and no subscription can exist)."""

from __future__ import annotations

from sqlalchemy.orm import Session

from app.core.models import Event


def fan_out(session: Session, event: Event) -> int:
    """Create a pending delivery per active subscription matching ``event``; returns how
    many. No subscriptions can be created yet, so there is nothing to deliver."""
    del session, event
    return 0
