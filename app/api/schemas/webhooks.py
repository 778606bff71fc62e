from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any

from pydantic import BaseModel, BeforeValidator, Field

from app.api.schemas.common import Model
from app.core.enums import DeliveryState, EventType
from app.core.models import Delivery, DeliveryAttempt, Event
from app.core.webhooks.adapters import WebhookFormat


def _known_format(value: Any) -> Any:
    """Refuse an unknown format naming it (the enum's own message does not)."""
    if isinstance(value, str) and value not in {f.value for f in WebhookFormat}:
        known = ", ".join(f.value for f in WebhookFormat)
        raise ValueError(f"unknown format {value!r}; one of {known}")
    return value


FORMAT_DESCRIPTION = (
    "the body: `cloudevents` (one CloudEvents 1.0 JSON per event, every type), "
    "`azure-digital-twins` (a JSON Patch per changed twin instance, for Update DigitalTwin) "
    "or `eclipse-ditto` (a JSON merge patch per changed thing); the two adapters receive "
    "only twin.updated"
)


class WebhookCreate(BaseModel):
    url: str = Field(
        min_length=1,
        max_length=2000,
        description="http(s) URL; private addresses only when allowed by the operator",
    )
    event_types: list[EventType] | None = Field(
        default=None, description="the event types to send; default every type"
    )
    environment_id: str | None = Field(
        default=None, description="only events of this environment; default every one"
    )
    format: Annotated[WebhookFormat, BeforeValidator(_known_format)] = Field(
        default=WebhookFormat.cloudevents, description=FORMAT_DESCRIPTION
    )


class WebhookRead(Model):
    id: str
    url: str
    event_types: list[EventType]
    environment_id: str | None
    format: WebhookFormat = Field(description=FORMAT_DESCRIPTION)
    active: bool
    created_at: datetime
    deactivated_at: datetime | None
    previous_secret_expires_at: datetime | None = Field(
        description="after a secret rotation: until then deliveries carry a signature made "
        "with the previous secret too (webhook-signature: 'v1,<new> v1,<previous>')"
    )


class WebhookCreated(WebhookRead):
    secret: str = Field(
        description="whsec_<base64>: the signing key (Standard Webhooks); shown only in this "
        "response (it is stored encrypted)"
    )


class AttemptRead(Model):
    number: int
    attempted_at: datetime
    status_code: int | None
    latency_ms: float | None
    response_excerpt: str | None = Field(description="the first 1 KB of the response body")
    error: str | None


class DeliveryRead(BaseModel):
    id: str
    webhook: str
    event: str = Field(description="the event id")
    event_type: EventType
    subject: str | None
    instance_id: str | None = Field(
        description="platform adapter formats: the twin instance whose patch this delivery "
        "carries (webhook-id is then '<event>:<instance_id>'; otherwise the event id)"
    )
    state: DeliveryState
    next_attempt_at: datetime | None
    last_status_code: int | None
    last_error: str | None
    created_at: datetime
    finished_at: datetime | None
    attempts: list[AttemptRead]

    @classmethod
    def of(cls, delivery: Delivery, event: Event, attempts: list[DeliveryAttempt]) -> DeliveryRead:
        return cls(
            id=delivery.id,
            webhook=delivery.subscription_id,
            event=event.id,
            event_type=EventType(event.type),
            subject=event.subject,
            instance_id=delivery.instance_id,
            state=delivery.state,
            next_attempt_at=(
                delivery.next_attempt_at if delivery.state == DeliveryState.pending else None
            ),
            last_status_code=delivery.last_status_code,
            last_error=delivery.last_error,
            created_at=delivery.created_at,
            finished_at=delivery.finished_at,
            attempts=[AttemptRead.model_validate(a) for a in attempts],
        )
