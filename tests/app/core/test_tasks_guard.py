"""A task that cannot even start its job fails the job with the reason and a job.failed
event, instead of leaving it queued for ever."""

from __future__ import annotations

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from app.core import jobs
from app.core.enums import EventType, JobKind, JobState
from app.core.models import Event
from tests.app.conftest import SentTasks


def test_import_failure_fails_the_queued_job(
    session_factory: sessionmaker[Session], sent_tasks: SentTasks
) -> None:
    from workers.tasks import _run

    with session_factory.begin() as s:
        job_id = jobs.create(s, JobKind.object, "object.prepare").id
    assert _run(job_id, "workers.no_such_module") == "failed"
    with session_factory.begin() as s:
        job = jobs.get(s, job_id)
        assert job.state == JobState.failed and job.error_code == "InternalError"
        assert "no_such_module" in (job.error_detail or "")
        types = s.scalars(select(Event.type)).all()
        assert EventType.job_failed in types
    # a job already taken by a worker is left alone
    assert _run(job_id, "workers.no_such_module") == "failed"
    with session_factory.begin() as s:
        assert jobs.get(s, job_id).finished_at is not None
