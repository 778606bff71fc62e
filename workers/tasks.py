"""Thin Celery tasks: each takes an id and hands over to a glue module that claims the job,
runs the pure pipeline and persists (see workers/runner.py). Task names are stable dotted
strings (app/core/queue.py routes them), never module paths.

The glue modules are imported inside the tasks, so the worker's parent process stays free
of Open3D/pycolmap (and their thread pools) when it forks its pool.
"""

from __future__ import annotations

import logging

from app.core import jobs
from app.core.db import transaction
from app.core.settings import get_settings
from workers.celery_app import app

log = logging.getLogger(__name__)


@app.task(name="snapshot.process")
def process_snapshot(job_id: str) -> str:
    """Ingest re-read → reconstruction → automatic comparison with the previous snapshot."""
    from workers import snapshot

    return snapshot.process(job_id)


@app.task(name="comparison.run")
def run_comparison(job_id: str) -> str:
    """Change detection, identification and pose for one comparison job."""
    from workers import comparison

    return comparison.run(job_id)


@app.task(name="object.prepare")
def prepare_object(job_id: str) -> str:
    """Sample a library model, measure it and detect its symmetry."""
    from workers import objects

    return objects.process(job_id)


@app.task(name="maintenance.sweep")
def sweep() -> dict[str, int]:
    """Re-send lost queued jobs; requeue or fail running jobs whose heartbeat stopped."""
    from workers.runner import on_failure_of, record_job_failed

    with transaction() as session:
        counts = jobs.sweep(session, get_settings())
        for job in session.info.pop("failed_jobs", []):
            handler = on_failure_of(job.kind)
            if handler is not None:
                handler(session, job, job.error_code or "WorkerLost", job.error_detail or "")
            record_job_failed(session, job)
    if any(counts.values()):
        log.info("sweep: %s", counts)
    return counts
