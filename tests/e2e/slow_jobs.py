"""A Celery worker extension for fault tests: ``celery worker --include tests.e2e.slow_jobs``.

In each pool process it puts a long first stage in front of the real object job's
computation (``workers.objects._compute``, which the job's ``run`` looks up when it runs): for
``TWINDELTA_TEST_SLOW_STAGE_S`` seconds the job reports progress every 50 ms, as a
reconstruction does, and then prepares the model for real. A fault injected while the job
shows the stage ``warmup`` lands in the middle of a running job, on its progress writes.

Patched in ``worker_process_init`` (after the fork), so the worker's parent process stays
free of Open3D, as in production.
"""

from __future__ import annotations

import os
import time
from typing import Any

from celery.signals import worker_process_init

STAGE = "warmup"


@worker_process_init.connect
def _slow_object_jobs(**_kwargs: Any) -> None:
    from workers import objects

    seconds = float(os.environ.get("TWINDELTA_TEST_SLOW_STAGE_S", "8"))
    real = objects._compute

    def slow_then_real(ctx: Any) -> Any:
        started = time.monotonic()
        while (elapsed := time.monotonic() - started) < seconds:
            ctx.progress(STAGE, elapsed / seconds)
            time.sleep(0.05)
        return real(ctx)

    objects._compute = slow_then_real  # type: ignore[assignment]
