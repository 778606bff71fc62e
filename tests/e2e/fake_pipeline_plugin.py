"""A Celery worker plugin for end-to-end tests of the service around the pipeline:
``celery -A workers.celery_app worker --include tests.e2e.fake_pipeline_plugin`` puts the
fake pipeline of :mod:`tests.workers.fake_pipeline` in place in every pool process, through
Celery's own ``--include`` option and ``worker_process_init`` signal (nothing in the
production code knows about it)."""

from __future__ import annotations

from typing import Any

from celery.signals import worker_process_init


@worker_process_init.connect
def install_fake_pipeline(**_kwargs: Any) -> None:
    from tests.workers import fake_pipeline

    fake_pipeline.install()
