"""What a receiver gets: an event as a CloudEvents 1.0 structured JSON body."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any

from app.core.eventschema import dataschema
from app.core.models import Event


def cloudevent(event: Event) -> dict[str, Any]:
    """The CloudEvents 1.0 structured form of an event; ``data`` is passed verbatim and
    ``dataschema`` names its JSON Schema (:mod:`app.core.eventschema`)."""
    source = (
        f"/twindelta/environments/{event.environment_id}" if event.environment_id else "/twindelta"
    )
    body: dict[str, Any] = {
        "specversion": "1.0",
        "id": event.id,
        "source": source,
        "type": str(event.type),
        "time": aware(event.created_at).isoformat().replace("+00:00", "Z"),
        "datacontenttype": "application/json",
        "dataschema": dataschema(str(event.type)),
        "data": event.data,
    }
    if event.subject is not None:
        body["subject"] = event.subject
    return body


def aware(value: datetime) -> datetime:
    """SQLite returns naive datetimes; they are UTC."""
    return value if value.tzinfo else value.replace(tzinfo=UTC)
