"""``/metrics`` in Prometheus text format: HTTP requests and latencies of this process, and
job counts by kind and state plus job durations, read from the database at scrape time (so
every API replica reports the same job figures)."""

from __future__ import annotations

import time
from collections.abc import Iterator

from fastapi import APIRouter, Response
from prometheus_client import (
    CONTENT_TYPE_LATEST,
    CollectorRegistry,
    Counter,
    Histogram,
    generate_latest,
)
from prometheus_client.core import GaugeMetricFamily, SummaryMetricFamily
from prometheus_client.registry import Collector
from sqlalchemy import func, select
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app.api.deps import MetricsKey
from app.api.schemas.common import ERRORS
from app.core import retention
from app.core.db import get_read_session_factory
from app.core.models import Job
from app.core.settings import get_settings

REGISTRY = CollectorRegistry()
REQUESTS = Counter(
    "twindelta_http_requests_total",
    "HTTP requests by method, route and status",
    ["method", "route", "status"],
    registry=REGISTRY,
)
LATENCY = Histogram(
    "twindelta_http_request_duration_seconds",
    "HTTP request latency by method and route",
    ["method", "route"],
    buckets=(0.002, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 10, 60),
    registry=REGISTRY,
)


class JobCollector(Collector):
    """Job counts by (kind, state) and finished-job durations by kind, from the database."""

    def collect(self) -> Iterator[GaugeMetricFamily | SummaryMetricFamily]:
        counts = GaugeMetricFamily(
            "twindelta_jobs", "Jobs by kind and state", labels=["kind", "state"]
        )
        durations = SummaryMetricFamily(
            "twindelta_job_duration_seconds", "Run time of finished jobs", labels=["kind"]
        )
        with get_read_session_factory().begin() as session:
            for kind_name, state, n in session.execute(
                select(Job.kind, Job.state, func.count()).group_by(Job.kind, Job.state)
            ):
                counts.add_metric([str(kind_name), str(state)], float(n))
            rows = session.execute(
                select(Job.kind, Job.started_at, Job.finished_at).where(
                    Job.started_at.is_not(None), Job.finished_at.is_not(None)
                )
            ).all()
        per_kind: dict[str, list[float]] = {}
        for job_kind, started, finished in rows:
            if started is not None and finished is not None:
                seconds = (finished - started).total_seconds()
                per_kind.setdefault(str(job_kind), []).append(seconds)
        for kind_label, values in per_kind.items():
            durations.add_metric([kind_label], count_value=len(values), sum_value=sum(values))
        yield counts
        yield durations


class StorageCollector(Collector):
    """Size, used and free bytes of the file system holding the storage folder, so an alert
    can fire before uploads and reconstructions fail for want of disk (see retention)."""

    def collect(self) -> Iterator[GaugeMetricFamily]:
        root = get_settings().resolved_storage_dir
        while not root.exists() and root != root.parent:  # not created yet: its file system
            root = root.parent
        try:
            usage = retention.disk_usage(root)
        except OSError:
            return
        for name, text, value in (
            ("twindelta_storage_size_bytes", "Storage file system size", usage.total_bytes),
            ("twindelta_storage_used_bytes", "Storage file system bytes used", usage.used_bytes),
            ("twindelta_storage_free_bytes", "Storage file system bytes free", usage.free_bytes),
        ):
            yield GaugeMetricFamily(name, text, value=float(value))


REGISTRY.register(JobCollector())
REGISTRY.register(StorageCollector())
router = APIRouter(tags=["health"])


@router.get("/metrics", response_class=Response, responses=ERRORS)
def metrics(_key: MetricsKey) -> Response:
    """Prometheus metrics: requests, latencies, jobs by kind and state, job durations. Needs
    a key with the ``metrics`` scope (``read`` and ``admin`` imply it; a key limited to
    environments does not get it, since the figures cover every environment)."""
    return Response(generate_latest(REGISTRY), media_type=CONTENT_TYPE_LATEST)


class MetricsMiddleware:
    """Pure ASGI middleware counting requests and timing them by route template."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = time.perf_counter()
        status = 500

        async def send_and_record(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = int(message["status"])
            await send(message)

        try:
            await self.app(scope, receive, send_and_record)
        finally:
            path = getattr(scope.get("route"), "path", "unmatched")
            LATENCY.labels(scope["method"], path).observe(time.perf_counter() - started)
            REQUESTS.labels(scope["method"], path, str(status)).inc()
