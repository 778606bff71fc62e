"""Thin webhook tasks. The schedule lives in the database (app/core/webhooks/):
``webhooks.deliver`` (``webhooks`` queue) makes one attempt, bounded by its deadline, and
never sleeps; beat's ``webhooks.dispatch`` (``maintenance`` queue, another worker process, so
deliveries that hang cannot hold it up) sends every delivery whose next attempt has come
due."""

from __future__ import annotations

import logging

from app.core import webhooks
from app.core.db import transaction
from app.core.settings import get_settings
from workers.celery_app import app

log = logging.getLogger(__name__)


@app.task(name="webhooks.deliver")
def deliver(delivery_id: str) -> str:
    """One attempt for the ordering key of ``delivery_id``: claim → POST (no session) → log."""
    settings = get_settings()
    with transaction() as session:
        claim = webhooks.claim(session, delivery_id, settings)
    if claim is None:
        return "skipped"
    outcome = webhooks.send(claim, settings)
    with transaction() as session:
        return webhooks.record_attempt(session, claim, outcome, settings)


@app.task(name="webhooks.dispatch")
def dispatch() -> int:
    """Send a deliver message for every delivery whose next attempt has come due."""
    with transaction() as session:
        sent = webhooks.dispatch_due(session)
    if sent:
        log.info("webhooks: dispatched %d due deliveries", len(sent))
    return len(sent)
