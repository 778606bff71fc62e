"""Progress reporting from the pure pipeline to the job row.

The pipeline calls ``progress(stage, fraction)``; writes are throttled to one every
``interval_s`` (stage changes are written at once), and each write reads the cancel intent:
when the user cancelled, the next call raises :class:`Cancelled` and the stage unwinds. A
heartbeat thread keeps ``heartbeat_at`` fresh while a long library call reports nothing.
A write that meets a transient database fault (a lock, a PostgreSQL restart) is skipped,
never raised into the computation: the next report writes again.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping

from app.core import jobs
from app.core.db import transaction
from workers.pipeline.errors import Cancelled
from workers.retry import is_transient

log = logging.getLogger(__name__)


class ProgressReporter:
    """``(stage, fraction) -> None`` bound to one running attempt of one job."""

    def __init__(self, job_id: str, attempt: int, interval_s: float, heartbeat_s: float) -> None:
        self.job_id, self.attempt = job_id, attempt
        self.interval_s, self.heartbeat_s = interval_s, heartbeat_s
        self._stage: str | None = None
        self._last_write = 0.0
        self._stop_requested = False
        self._lock = threading.Lock()
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._beat, name=f"heartbeat-{job_id}", daemon=True)

    def __call__(self, stage: str, fraction: float) -> None:
        now = time.monotonic()
        if stage != self._stage or now - self._last_write >= self.interval_s:
            self._stage = stage
            self._write(stage, fraction)
        if self._stop_requested:
            raise Cancelled("cancelled by request")

    def _write(self, stage: str | None, fraction: float | None) -> None:
        with self._lock:
            self._last_write = time.monotonic()
            try:
                with transaction() as session:
                    if jobs.report(session, self.job_id, self.attempt, stage, fraction):
                        self._stop_requested = True
            except Exception as exc:
                if not is_transient(exc):
                    raise
                log.warning(
                    "progress of job %s not written (next report retries): %s", self.job_id, exc
                )

    def _beat(self) -> None:
        while not self._done.wait(self.heartbeat_s):
            try:
                self._write(None, None)
            except Exception:  # a database hiccup must not kill the job; the next beat retries
                log.exception("heartbeat of job %s failed", self.job_id)

    def check_cancelled(self) -> None:
        """Raise Cancelled when the user asked to stop (read at the last write)."""
        if self._stop_requested:
            raise Cancelled("cancelled by request")

    def __enter__(self) -> ProgressReporter:
        self._thread.start()
        return self

    def __exit__(self, *_exc: object) -> None:
        self._done.set()
        self._thread.join(timeout=5)


Progress = Callable[[str, float], None]


def weighted(progress: Progress, weights: Mapping[str, float]) -> Progress:
    """Turn a stage's own 0..1 fraction into the job's overall 0..1 progress.

    Stages cover consecutive spans in the order of ``weights`` (normalised to sum 1); a
    stage named ``a.b`` counts as ``a`` when only ``a`` is listed. Unknown stages keep the
    overall figure, and it never goes backwards. The stage name is passed on unchanged.
    """
    total = sum(weights.values()) or 1.0
    starts: dict[str, float] = {}
    acc = 0.0
    for name, weight in weights.items():
        starts[name] = acc / total
        acc += weight
    overall = 0.0

    def report(stage: str, fraction: float) -> None:
        nonlocal overall
        key = stage if stage in weights else stage.split(".", 1)[0]
        if key in weights:
            span = weights[key] / total
            overall = max(overall, starts[key] + span * min(max(fraction, 0.0), 1.0))
        progress(stage, overall)

    return report
