"""Webhook subscriptions (admin) and their delivery log."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Query, status

from app.api.deps import AdminKey, ReadKey, SessionDep, SettingsDep
from app.api.schemas.common import ERRORS, TOO_LARGE, ErrorOut, conflict
from app.api.schemas.webhooks import (
    DeliveryRead,
    WebhookCreate,
    WebhookCreated,
    WebhookRead,
)
from app.core import webhooks
from app.core.enums import DeliveryState

router = APIRouter(prefix="/webhooks", tags=["webhooks"], responses=ERRORS)


@router.post("", status_code=status.HTTP_201_CREATED, responses=TOO_LARGE)
def create_webhook(
    body: WebhookCreate, session: SessionDep, settings: SettingsDep, _key: AdminKey
) -> WebhookCreated:
    """Subscribe a URL to events; the response is the only time the signing secret is shown."""
    sub = webhooks.create_subscription(
        session,
        settings,
        url=body.url,
        event_types=body.event_types,
        environment_id=body.environment_id,
        fmt=body.format,
    )
    secret = webhooks.current_secret(settings, sub)
    return WebhookCreated(**WebhookRead.model_validate(sub).model_dump(), secret=secret)


@router.get("/schemas/events")
def event_schema(_key: ReadKey) -> dict[str, Any]:
    """The JSON Schema (2020-12) of CloudEvents deliveries: `$defs/<event type>` is each
    type's `data`. Its `$id` (`urn:twindelta:events:1`) is what every event's `dataschema`
    points into (`urn:twindelta:events:1#/$defs/<type>`)."""
    return webhooks.event_schema()


@router.get("")
def list_webhooks(session: SessionDep, _key: AdminKey) -> list[WebhookRead]:
    """Every subscription, without secrets."""
    return [WebhookRead.model_validate(s) for s in webhooks.list_subscriptions(session)]


@router.get("/{webhook_id}")
def get_webhook(webhook_id: str, session: SessionDep, _key: AdminKey) -> WebhookRead:
    """One subscription, without its secret."""
    return WebhookRead.model_validate(webhooks.get_subscription(session, webhook_id))


@router.delete("/{webhook_id}")
def delete_webhook(webhook_id: str, session: SessionDep, _key: AdminKey) -> WebhookRead:
    """Deactivate a subscription: nothing more is sent and its pending deliveries end failed."""
    return WebhookRead.model_validate(webhooks.deactivate(session, webhook_id))


@router.post(
    "/{webhook_id}/rotate-secret",
    responses={409: {"model": ErrorOut, "description": "the webhook is deactivated"}},
)
def rotate_secret(
    webhook_id: str, session: SessionDep, settings: SettingsDep, _key: AdminKey
) -> WebhookCreated:
    """Give a webhook a new signing secret, shown only in this response. The previous secret
    keeps signing too until `previous_secret_expires_at` (TWINDELTA_WEBHOOK_SECRET_OVERLAP_S,
    default 24 h): each delivery then carries both signatures, space-separated in
    `webhook-signature`, so the receiver can switch to the new secret at any time within it."""
    sub, secret = webhooks.rotate_secret(session, settings, webhook_id)
    return WebhookCreated(**WebhookRead.model_validate(sub).model_dump(), secret=secret)


@router.get("/{webhook_id}/deliveries")
def list_deliveries(
    webhook_id: str,
    session: SessionDep,
    _key: AdminKey,
    state: DeliveryState | None = None,
    limit: Annotated[int, Query(ge=1, le=500)] = 100,
) -> list[DeliveryRead]:
    """The delivery log, newest first: every attempt with status, latency, response, error."""
    rows = webhooks.list_deliveries(session, webhook_id, state=state, limit=limit)
    return [DeliveryRead.of(d, e, a) for d, e, a in rows]


@router.post(
    "/{webhook_id}/deliveries/{delivery_id}/redeliver",
    status_code=status.HTTP_202_ACCEPTED,
    responses=conflict(
        "WebhookInactive: the webhook is deactivated; InFlight: an attempt is being sent"
    ),
)
def redeliver(
    webhook_id: str, delivery_id: str, session: SessionDep, _key: AdminKey
) -> DeliveryRead:
    """Send a delivery again with a fresh retry schedule (also a failed or succeeded one)."""
    delivery = webhooks.redeliver(session, webhook_id, delivery_id)
    return DeliveryRead.of(*webhooks.describe(session, delivery))
