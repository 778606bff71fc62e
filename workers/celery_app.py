"""The Celery application of the workers. Configuration comes from app.core.queue so the
sender (API) and the consumers can never disagree on queues, routes or acknowledgement."""

from __future__ import annotations

from celery import Celery

from app.core.queue import celery_config
from app.core.settings import get_settings

app = Celery(
    "twindelta", include=["workers.tasks", "workers.webhook_tasks", "workers.maintenance_tasks"]
)
app.conf.update(celery_config(get_settings()))
