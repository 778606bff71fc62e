"""Send Celery tasks by name, only after the enclosing transaction commits.

``enqueue(session, "snapshot.process", job_id=...)`` buffers on the session; an
``after_commit`` hook sends; a rollback drops the buffer. If the broker is down at that
moment the job row stays ``queued`` and the sweeper sends it again, so nothing is lost.
The Celery configuration lives here too, so the API (which only sends) and the workers
(which consume) can never disagree on queues and routes.
"""

from __future__ import annotations

import logging
from functools import lru_cache
from typing import Any

from celery import Celery
from sqlalchemy import event
from sqlalchemy.orm import Session

from app.core.settings import Settings, get_settings

log = logging.getLogger(__name__)

CPU_QUEUE = "cpu"
WEBHOOKS_QUEUE = "webhooks"
# Beat's periodic tasks have a queue and a worker process of their own: deliveries can take
# every thread of the webhooks worker (a slow receiver holds one until its deadline), and
# the dispatcher and the sweeper must not wait behind them.
MAINTENANCE_QUEUE = "maintenance"
TASK_QUEUES: dict[str, str] = {
    "snapshot.process": CPU_QUEUE,
    "comparison.run": CPU_QUEUE,
    "object.prepare": CPU_QUEUE,
    "webhooks.deliver": WEBHOOKS_QUEUE,
    "webhooks.dispatch": MAINTENANCE_QUEUE,
    "maintenance.sweep": MAINTENANCE_QUEUE,
    "maintenance.retention": MAINTENANCE_QUEUE,
    "maintenance.uploads": MAINTENANCE_QUEUE,
}
_PENDING = "twindelta_pending_tasks"


def celery_config(settings: Settings) -> dict[str, Any]:
    """Celery settings shared by the sender and the workers.

    acks_late + reject_on_worker_lost + prefetch 1: a message is acknowledged only after its
    task ran, so a killed worker's job is delivered again; tasks are idempotent, so that is
    safe. The visibility timeout is longer than the longest task.
    """
    transport_options: dict[str, Any] = {"visibility_timeout": settings.broker_visibility_timeout_s}
    if settings.is_embedded_broker:
        folder = settings.broker_dir
        for sub in ("out", "processed", "control"):
            (folder / sub).mkdir(parents=True, exist_ok=True)
        transport_options = {
            "data_folder_in": str(folder / "out"),
            "data_folder_out": str(folder / "out"),
            "processed_folder": str(folder / "processed"),
            "control_folder": str(folder / "control"),
            "store_processed": False,
        }
    return {
        "broker_url": settings.resolved_broker_url,
        "broker_transport_options": transport_options,
        "broker_connection_retry_on_startup": True,
        "task_routes": {name: {"queue": queue} for name, queue in TASK_QUEUES.items()},
        "task_default_queue": CPU_QUEUE,
        "task_acks_late": True,
        "task_reject_on_worker_lost": True,
        "task_ignore_result": True,
        "task_time_limit": settings.task_time_limit_s,
        "worker_prefetch_multiplier": 1,
        "worker_enable_remote_control": not settings.is_embedded_broker,
        "worker_send_task_events": False,
        "worker_hijack_root_logger": False,
        "timezone": "UTC",
        "beat_schedule": {
            "sweep": {"task": "maintenance.sweep", "schedule": settings.sweep_interval_s},
            "retention": {
                "task": "maintenance.retention",
                "schedule": settings.retention_interval_s,
            },
            "uploads": {
                "task": "maintenance.uploads",
                "schedule": settings.upload_sweep_interval_s,
            },
            "webhooks-dispatch": {
                "task": "webhooks.dispatch",
                "schedule": webhook_dispatch_interval_s(settings),
            },
        },
    }


def webhook_dispatch_interval_s(settings: Settings) -> float:
    """How often beat sends due webhook deliveries: as fine as the shortest retry delay,
    within 0.25–5 s (a retry cannot happen before the next tick)."""
    shortest = min(settings.webhook_retry_schedule_s, default=5.0)
    return min(max(float(shortest), 0.25), 5.0)


@lru_cache(maxsize=1)
def get_sender() -> Celery:
    """A Celery app used only to send messages (the API never imports the workers)."""
    app = Celery("twindelta-sender")
    app.conf.update(celery_config(get_settings()))
    return app


def send_now(task_name: str, **kwargs: Any) -> None:
    """Send immediately (outside any transaction); routes by task name."""
    if task_name not in TASK_QUEUES:
        raise KeyError(f"unknown task {task_name!r}")
    get_sender().send_task(task_name, kwargs=kwargs, queue=TASK_QUEUES[task_name])


def enqueue(session: Session, task_name: str, **kwargs: Any) -> None:
    """Send ``task_name`` with ``kwargs`` once ``session``'s transaction commits."""
    if task_name not in TASK_QUEUES:
        raise KeyError(f"unknown task {task_name!r}")
    session.info.setdefault(_PENDING, []).append((task_name, kwargs))


@event.listens_for(Session, "after_commit")
def _send_after_commit(session: Session) -> None:
    if session.in_nested_transaction():  # a released SAVEPOINT is not the commit
        return
    pending = session.info.pop(_PENDING, [])
    for task_name, kwargs in pending:
        try:
            send_now(task_name, **kwargs)
        except Exception:  # the sweeper re-sends queued jobs; never fail the request now
            log.exception("could not send %s %s; the sweeper will retry", task_name, kwargs)


@event.listens_for(Session, "after_soft_rollback")
def _drop_on_rollback(session: Session, previous_transaction: Any) -> None:
    # Only the outermost rollback drops the buffer; a SAVEPOINT rolled back inside a
    # transaction that still commits keeps what was enqueued before it.
    if previous_transaction.parent is None:
        session.info.pop(_PENDING, None)
