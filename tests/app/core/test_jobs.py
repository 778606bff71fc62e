"""The job state machine: atomic claim, fencing by attempt, cancel, and the sweeper."""

from __future__ import annotations

from datetime import timedelta

import pytest
from sqlalchemy.orm import Session, sessionmaker

from app.core import jobs
from app.core.enums import JobKind, JobState
from app.core.errors import Conflict
from app.core.models import utcnow
from app.core.settings import get_settings
from tests.app.conftest import SentTasks


def make_job(factory: sessionmaker[Session]) -> str:
    with factory.begin() as s:
        return jobs.create(s, JobKind.object, "object.prepare").id


def test_enqueued_only_after_commit(
    session_factory: sessionmaker[Session], sent_tasks: SentTasks
) -> None:
    with pytest.raises(RuntimeError), session_factory.begin() as s:
        jobs.create(s, JobKind.object, "object.prepare")
        raise RuntimeError("roll back")
    assert sent_tasks.calls == []
    job_id = make_job(session_factory)
    assert sent_tasks.calls == [("object.prepare", {"job_id": job_id})]


def test_claim_is_exclusive_and_fences_stale_attempts(
    session_factory: sessionmaker[Session], sent_tasks: SentTasks
) -> None:
    job_id = make_job(session_factory)
    with session_factory.begin() as s:
        first = jobs.claim(s, job_id, "w1")
    with session_factory.begin() as s:
        assert jobs.claim(s, job_id, "w2") is None  # already running
    assert first == 1
    with session_factory.begin() as s:
        assert jobs.report(s, job_id, 1, "stage-a", 0.5) is False
        assert jobs.get(s, job_id).progress == 0.5
    # a stale attempt number can neither report nor finish
    with session_factory.begin() as s:
        assert jobs.report(s, job_id, 7, "x", 0.9) is True
        assert jobs.finish(s, job_id, 7, JobState.succeeded) is None
    with session_factory.begin() as s:
        done = jobs.finish(s, job_id, 1, JobState.succeeded)
        assert done is not None and done.state == JobState.succeeded and done.progress == 1.0
    with session_factory.begin() as s:
        assert jobs.claim(s, job_id, "w3") is None  # final: a redelivered message is a no-op


def test_cancel_queued_running_and_final(
    session_factory: sessionmaker[Session], sent_tasks: SentTasks
) -> None:
    queued = make_job(session_factory)
    with session_factory.begin() as s:
        job = jobs.cancel(s, queued)
        assert job.state == JobState.cancelled
    with session_factory.begin() as s:
        assert jobs.claim(s, queued, "w") is None
    running = make_job(session_factory)
    with session_factory.begin() as s:
        attempt = jobs.claim(s, running, "w")
    assert attempt is not None
    with session_factory.begin() as s:
        assert jobs.cancel(s, running).state == JobState.running
    with session_factory.begin() as s:
        assert jobs.report(s, running, attempt, "work", 0.1) is True  # the worker is told
    with session_factory.begin() as s, pytest.raises(Conflict):
        jobs.cancel(s, queued)


def test_sweeper_resends_requeues_and_fails(
    session_factory: sessionmaker[Session], sent_tasks: SentTasks
) -> None:
    settings = get_settings()
    lost = make_job(session_factory)
    dead = make_job(session_factory)
    exhausted = make_job(session_factory)
    with session_factory.begin() as s:
        for job_id in (dead, exhausted):
            jobs.claim(s, job_id, "w")
        jobs.get(s, exhausted).attempts = settings.max_job_attempts
    sent_tasks.calls.clear()
    later = utcnow() + timedelta(
        seconds=settings.heartbeat_timeout_s + settings.requeue_after_s + 1
    )
    with session_factory.begin() as s:
        counts = jobs.sweep(s, settings, now=later)
    assert counts == {"resent": 1, "requeued": 1, "failed": 1, "cancelled": 0, "errors": 0}
    assert sorted(kw["job_id"] for _, kw in sent_tasks.calls) == sorted([lost, dead])
    with session_factory.begin() as s:
        assert jobs.get(s, dead).state == JobState.queued
        gone = jobs.get(s, exhausted)
        assert gone.state == JobState.failed and gone.error_code == "WorkerLost"
    # right after a send, nothing is resent again (the wait doubles)
    sent_tasks.calls.clear()
    with session_factory.begin() as s:
        assert jobs.sweep(s, settings, now=later + timedelta(seconds=1))["resent"] == 0


def test_savepoint_release_does_not_send_early(
    session_factory: sessionmaker[Session], sent_tasks: SentTasks
) -> None:
    with session_factory.begin() as s:
        job = jobs.create(s, JobKind.object, "object.prepare")
        with s.begin_nested():
            pass  # releasing a SAVEPOINT must not flush the buffer
        assert sent_tasks.calls == []
        with pytest.raises(RuntimeError), s.begin_nested():
            raise RuntimeError("a savepoint rolled back keeps the outer buffer")
        assert sent_tasks.calls == []
    assert sent_tasks.calls == [("object.prepare", {"job_id": job.id})]
