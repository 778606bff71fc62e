"""Storage maintenance on beat's schedule (``maintenance.retention``, every
``retention_interval_s``): the retention policy from the settings, then the cleanup of what
killed processes left (app/core/retention.py); and (``maintenance.uploads``, every
``upload_sweep_interval_s``) expired resumable uploads (app/core/uploads.py). Files go only
after each transaction commits. Every worker process also sweeps its own host's job work
folders when it starts (:func:`sweep_own_scratch`): no other host sees them."""

from __future__ import annotations

import logging

from celery.signals import worker_ready

from app.core import retention as policy
from app.core import uploads
from app.core.db import transaction
from app.core.settings import get_settings
from app.core.storage import open_storage
from workers.celery_app import app

log = logging.getLogger(__name__)


@app.task(name="maintenance.retention")
def retention() -> dict[str, int]:
    """Apply the retention policy, then remove stale work folders, staging and orphans."""
    settings = get_settings()
    storage = open_storage(settings)
    with transaction() as session:
        counts = policy.apply_policy(session, storage, policy.Policy.from_settings(settings))
    with transaction() as session:
        counts.update(policy.cleanup_files(session, storage, settings.stale_files_after_s))
    if any(counts.values()):
        log.info("retention: %s", counts)
    return counts


@app.task(name="maintenance.uploads")
def expire_uploads() -> dict[str, int]:
    """Delete expired resumable uploads with their bytes, and partial files with no upload."""
    settings = get_settings()
    storage = open_storage(settings)
    with transaction() as session:
        counts = uploads.expire(session, storage, settings.stale_files_after_s)
    if any(counts.values()):
        log.info("uploads: %s", counts)
    return counts


@worker_ready.connect
def sweep_own_scratch(**_: object) -> int:
    """At a worker's start, remove the work folders its host's killed workers left
    (:func:`policy.sweep_work`); a database that is not up yet only skips it. Returns how
    many."""
    storage = open_storage(get_settings())
    try:
        with transaction() as session:
            removed = policy.sweep_work(session, storage)
    except Exception:  # the start must not fail on a sweep; the next start tries again
        log.warning("could not sweep this host's work folders at start", exc_info=True)
        return 0
    if removed:
        log.info("removed %d work folders of jobs that ended", removed)
    return removed
