"""Webhook subscriptions: create (target checked, fresh secret), list, deactivate, and their
signing secrets (stored encrypted with :mod:`app.core.secretbox`; rotation with an overlap)."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from datetime import datetime, timedelta

from sqlalchemy import select, update
from sqlalchemy.orm import Session

from app.core import secretbox
from app.core.enums import DeliveryState, EventType
from app.core.errors import Conflict, InvalidInput, NotFound
from app.core.models import Delivery, Environment, WebhookSubscription, utcnow
from app.core.settings import Settings
from app.core.webhooks.adapters import ADAPTER_EVENT_TYPES, WebhookFormat
from app.core.webhooks.payload import aware
from app.core.webhooks.signing import new_secret
from app.core.webhooks.targets import allowed_networks, check_target


def create_subscription(
    session: Session,
    settings: Settings,
    *,
    url: str,
    event_types: Iterable[EventType] | None,
    environment_id: str | None,
    fmt: str = WebhookFormat.cloudevents,
) -> WebhookSubscription:
    """A new active subscription with a fresh secret (the caller shows it once).

    ``fmt`` is a :class:`WebhookFormat` (422 naming it otherwise). A platform adapter
    format receives only ``twin.updated`` (one patch per changed instance); its
    ``event_types`` default to that, and any other type is refused (422)."""
    body_format = _format(fmt)
    check_target(url, allowed_networks(settings))
    types = _event_types(body_format, event_types)
    if environment_id is not None and session.get(Environment, environment_id) is None:
        raise InvalidInput(f"environment_id: environment {environment_id} not found")
    sub = WebhookSubscription(
        url=url,
        event_types=[str(t) for t in types],
        environment_id=environment_id,
        secret_encrypted=secretbox.encrypt(settings, new_secret()),
        active=True,
        format=str(body_format),
    )
    session.add(sub)
    session.flush()
    return sub


def _format(value: str) -> WebhookFormat:
    try:
        return WebhookFormat(value)
    except ValueError:
        known = ", ".join(f.value for f in WebhookFormat)
        raise InvalidInput(f"format: unknown format {value!r}; one of {known}") from None


def _event_types(fmt: WebhookFormat, asked: Iterable[EventType] | None) -> list[EventType]:
    if fmt == WebhookFormat.cloudevents:
        return sorted({EventType(t) for t in asked} if asked else set(EventType))
    types = {EventType(t) for t in asked} if asked else set(ADAPTER_EVENT_TYPES)
    other = sorted(types - ADAPTER_EVENT_TYPES)
    if other:
        raise InvalidInput(
            f"event_types: format {fmt} sends only "
            f"{', '.join(sorted(ADAPTER_EVENT_TYPES))} (one patch per changed twin instance); "
            f"not {', '.join(other)}"
        )
    return sorted(types)


def current_secret(settings: Settings, sub: WebhookSubscription) -> str:
    """The subscription's signing secret in plain text (stored encrypted)."""
    return secretbox.decrypt(settings, sub.secret_encrypted)


def signing_secrets(
    settings: Settings, sub: WebhookSubscription, now: datetime | None = None
) -> tuple[str, ...]:
    """The secrets a delivery is signed with now: the current one, and the previous one while
    a rotation's overlap lasts (Standard Webhooks: one signature each, space-separated)."""
    now = now or utcnow()
    out = [current_secret(settings, sub)]
    expires = sub.previous_secret_expires_at
    if sub.previous_secret_encrypted and expires is not None and aware(expires) > now:
        out.append(secretbox.decrypt(settings, sub.previous_secret_encrypted))
    return tuple(out)


def reencrypt_secrets(session: Session, settings: Settings) -> int:
    """Re-encrypt every stored signing secret under the newest TWINDELTA_SECRET_KEY (after
    the key was changed to "new,old"); then the old key can be dropped. Returns how many."""
    count = 0
    for sub in session.scalars(select(WebhookSubscription)):
        sub.secret_encrypted = secretbox.reencrypt(settings, sub.secret_encrypted)
        if sub.previous_secret_encrypted:
            sub.previous_secret_encrypted = secretbox.reencrypt(
                settings, sub.previous_secret_encrypted
            )
        count += 1
    session.flush()
    return count


def rotate_secret(
    session: Session, settings: Settings, subscription_id: str, now: datetime | None = None
) -> tuple[WebhookSubscription, str]:
    """Give a subscription a new secret; returns it in plain text (the caller shows it once).

    The current secret becomes the previous one and keeps signing, next to the new one, for
    ``Settings.webhook_secret_overlap_s``; a previous secret from an earlier rotation is
    dropped. 409 for a deactivated subscription."""
    sub = get_subscription(session, subscription_id)
    if not sub.active:
        raise Conflict(f"webhook {sub.id} is deactivated", code="WebhookInactive")
    now = now or utcnow()
    secret = new_secret()
    overlap = settings.webhook_secret_overlap_s
    sub.previous_secret_encrypted = sub.secret_encrypted if overlap > 0 else None
    sub.previous_secret_expires_at = now + timedelta(seconds=overlap) if overlap > 0 else None
    sub.secret_encrypted = secretbox.encrypt(settings, secret)
    session.flush()
    return sub, secret


def get_subscription(session: Session, subscription_id: str) -> WebhookSubscription:
    sub = session.get(WebhookSubscription, subscription_id)
    if sub is None:
        raise NotFound(f"webhook {subscription_id} not found")
    return sub


def list_subscriptions(session: Session) -> Sequence[WebhookSubscription]:
    return session.scalars(
        select(WebhookSubscription).order_by(WebhookSubscription.created_at)
    ).all()


def deactivate(session: Session, subscription_id: str) -> WebhookSubscription:
    """Stop a subscription: no new deliveries, and its pending ones end as failed."""
    sub = get_subscription(session, subscription_id)
    now = utcnow()
    if sub.active:
        sub.active, sub.deactivated_at = False, now
    session.execute(
        update(Delivery)
        .where(Delivery.subscription_id == sub.id, Delivery.state == DeliveryState.pending)
        .values(state=DeliveryState.failed, finished_at=now, last_error="subscription deactivated")
    )
    session.flush()
    return sub
