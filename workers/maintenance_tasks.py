"""Storage maintenance on beat's schedule (``maintenance.retention``, every
``retention_interval_s``): the retention policy from the settings, then the cleanup of what
killed processes left (app/core/retention.py); and (``maintenance.uploads``, every
``upload_sweep_interval_s``) expired resumable uploads (app/core/uploads.py). Files go only
after each transaction commits."""

from __future__ import annotations

import logging

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
