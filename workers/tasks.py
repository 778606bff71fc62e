"""Thin Celery tasks: each takes an id and hands over to a glue module (``run(job_id)``) that
claims the job, runs the pure pipeline and persists (see workers/runner.py). Task names are
stable dotted strings (app/core/queue.py routes them), never module paths.

The glue modules are imported inside the tasks, so the worker's parent process stays free
of Open3D/pycolmap (and their thread pools) when it forks its pool.
"""

from __future__ import annotations

import importlib
import logging

from app.core import jobs, lifecycle
from app.core.db import transaction
from app.core.settings import get_settings
from workers.celery_app import app

log = logging.getLogger(__name__)


def _run(job_id: str, module: str) -> str:
    """Import ``module`` and run the job. A failure before the job is claimed (a broken
    install, an import error) fails the job with its reason instead of leaving it queued
    for the sweeper to send again and again."""
    try:
        glue = importlib.import_module(module)
    except Exception as exc:
        log.exception("cannot start job %s: %s does not import", job_id, module)
        with transaction() as session:
            job = jobs.fail_unclaimed(
                session,
                job_id,
                "InternalError",
                f"worker cannot start: {type(exc).__name__}: {exc}",
            )
            if job is not None:
                lifecycle.settle(session, job)
        return "failed"
    outcome: str = glue.run(job_id)
    return outcome


@app.task(name="snapshot.process")
def process_snapshot(job_id: str) -> str:
    """Ingest re-read → reconstruction → automatic comparison with the previous snapshot."""
    return _run(job_id, "workers.snapshot")


@app.task(name="comparison.run")
def run_comparison(job_id: str) -> str:
    """Change detection, identification and pose for one comparison job."""
    return _run(job_id, "workers.comparison")


@app.task(name="object.prepare")
def prepare_object(job_id: str) -> str:
    """Sample a library model, measure it and detect its symmetry."""
    return _run(job_id, "workers.objects")


@app.task(name="maintenance.sweep")
def sweep() -> dict[str, int]:
    """Re-send lost queued jobs; requeue or fail running jobs whose heartbeat stopped (each
    job on its own: one that cannot be handled is logged and never stops the others)."""
    with transaction() as session:
        counts = jobs.sweep(session, get_settings())
    if counts["errors"]:
        log.error("sweep: %s", counts)
    elif any(counts.values()):
        log.info("sweep: %s", counts)
    return counts
