"""The runner: claim → compute → persist, and what it does when the job's subject is gone,
when the user cancels, and when the database has a transient fault (a lock held for longer
than the busy timeout, a PostgreSQL restart): progress writes skip, the final write retries,
and a database down past ``db_retry_s`` leaves the job to the sweeper instead of failing it."""

from __future__ import annotations

import sqlite3
from collections.abc import Callable, Iterator
from datetime import timedelta
from typing import Any

import pytest
from sqlalchemy import select
from sqlalchemy.exc import OperationalError
from sqlalchemy.orm import Session, sessionmaker

from app.core import jobs
from app.core.enums import EventType, JobKind, JobState, ObjectState
from app.core.models import Event, LibraryObject, utcnow
from app.core.settings import get_settings
from tests.app.conftest import SentTasks
from workers.runner import JobContext, run_job


def locked() -> OperationalError:
    """What SQLAlchemy raises when SQLite's busy timeout runs out under another writer."""
    return OperationalError("UPDATE jobs", {}, sqlite3.OperationalError("database is locked"))


@pytest.fixture
def fast(monkeypatch: pytest.MonkeyPatch, data_dir: object) -> Iterator[None]:
    """Progress written at every report, and a short database retry bound."""
    monkeypatch.setenv("TWINDELTA_PROGRESS_INTERVAL_S", "0")
    monkeypatch.setenv("TWINDELTA_DB_RETRY_S", "1")
    get_settings.cache_clear()
    yield
    get_settings.cache_clear()


def make_object_job(factory: sessionmaker[Session]) -> tuple[str, str]:
    with factory.begin() as s:
        obj = LibraryObject(name="box", filename="box.ply", file_key="objects/x", size_bytes=1)
        s.add(obj)
        s.flush()
        return obj.id, jobs.create(s, JobKind.object, "object.prepare", object_id=obj.id).id


def flaky(real: Callable[..., Any], failures: int) -> Callable[..., Any]:
    """``real`` that raises a transient OperationalError on its first ``failures`` calls."""
    calls = {"n": 0}

    def call(*args: Any, **kwargs: Any) -> Any:
        calls["n"] += 1
        if calls["n"] <= failures:
            raise locked()
        return real(*args, **kwargs)

    return call


def persist_marks_ready(calls: list[str]) -> Callable[[Session, JobContext, str], None]:
    def persist(session: Session, ctx: JobContext, result: str) -> None:
        calls.append(result)
        obj = session.get(LibraryObject, ctx.job.object_id)
        assert obj is not None
        obj.state = ObjectState.ready

    return persist


def events_of(s: Session, job_id: str) -> list[str]:
    return [str(t) for t in s.scalars(select(Event.type).where(Event.subject == f"jobs/{job_id}"))]


def test_progress_writes_survive_a_locked_database(
    session_factory: sessionmaker[Session],
    sent_tasks: SentTasks,
    fast: None,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    object_id, job_id = make_object_job(session_factory)
    monkeypatch.setattr(jobs, "report", flaky(jobs.report, failures=3))
    persisted: list[str] = []

    def compute(ctx: JobContext) -> str:
        for i in range(6):
            ctx.progress("work", i / 5)
        return "model"

    assert run_job(job_id, compute, persist_marks_ready(persisted)) == "succeeded"
    assert persisted == ["model"]
    with session_factory.begin() as s:
        job = jobs.get(s, job_id)
        assert job.state == JobState.succeeded and job.attempts == 1 and job.error_code is None
        obj = s.get(LibraryObject, object_id)
        assert obj is not None and obj.state == ObjectState.ready


def test_the_final_write_is_retried_and_persists_once(
    session_factory: sessionmaker[Session],
    sent_tasks: SentTasks,
    fast: None,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    _object_id, job_id = make_object_job(session_factory)
    monkeypatch.setattr(jobs, "finish", flaky(jobs.finish, failures=2))
    persisted: list[str] = []
    assert run_job(job_id, lambda ctx: "model", persist_marks_ready(persisted)) == "succeeded"
    assert persisted == ["model"]
    with session_factory.begin() as s:
        job = jobs.get(s, job_id)
        assert job.state == JobState.succeeded and job.attempts == 1
        assert events_of(s, job_id) == []


def test_a_database_down_past_the_bound_leaves_the_job_to_the_sweeper(
    session_factory: sessionmaker[Session],
    sent_tasks: SentTasks,
    fast: None,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    _object_id, job_id = make_object_job(session_factory)
    real_finish = jobs.finish
    monkeypatch.setattr(jobs, "finish", flaky(real_finish, failures=10_000))
    persisted: list[str] = []
    assert run_job(job_id, lambda ctx: "model", persist_marks_ready(persisted)) == "deferred"
    assert persisted == []
    with session_factory.begin() as s:
        job = jobs.get(s, job_id)  # not failed: still this attempt's, heartbeat stopping
        assert job.state == JobState.running and job.error_code is None
    monkeypatch.setattr(jobs, "finish", real_finish)
    settings = get_settings()
    sent_tasks.calls.clear()
    with session_factory.begin() as s:
        later = utcnow() + timedelta(seconds=settings.heartbeat_timeout_s + 1)
        assert jobs.sweep(s, settings, now=later)["requeued"] == 1
    assert sent_tasks.calls == [("object.prepare", {"job_id": job_id})]
    assert run_job(job_id, lambda ctx: "model", persist_marks_ready(persisted)) == "succeeded"
    assert persisted == ["model"]
    with session_factory.begin() as s:
        assert jobs.get(s, job_id).attempts == 2


def test_a_transient_error_in_compute_requeues_the_job(
    session_factory: sessionmaker[Session], sent_tasks: SentTasks, fast: None
) -> None:
    object_id, job_id = make_object_job(session_factory)
    sent_tasks.calls.clear()

    def compute(ctx: JobContext) -> str:
        raise locked()

    assert run_job(job_id, compute, persist_marks_ready([])) == "requeued"
    assert sent_tasks.calls == [("object.prepare", {"job_id": job_id})]
    with session_factory.begin() as s:
        job = jobs.get(s, job_id)
        assert job.state == JobState.queued and job.attempts == 1 and job.worker is None
        assert events_of(s, job_id) == []
        obj = s.get(LibraryObject, object_id)
        assert obj is not None and obj.state == ObjectState.processing


def test_a_transient_error_on_the_last_attempt_fails_the_job(
    session_factory: sessionmaker[Session], sent_tasks: SentTasks, fast: None
) -> None:
    object_id, job_id = make_object_job(session_factory)
    with session_factory.begin() as s:
        jobs.get(s, job_id).attempts = get_settings().max_job_attempts - 1

    def compute(ctx: JobContext) -> str:
        raise locked()

    assert run_job(job_id, compute, persist_marks_ready([])) == "failed"
    with session_factory.begin() as s:
        job = jobs.get(s, job_id)
        assert job.state == JobState.failed and job.error_code == "DatabaseUnavailable"
        assert "database is locked" in (job.error_detail or "")
        assert events_of(s, job_id) == [EventType.job_failed]
        obj = s.get(LibraryObject, object_id)
        assert obj is not None and obj.state == ObjectState.failed


def test_a_job_whose_object_was_deleted_fails_cleanly(
    session_factory: sessionmaker[Session], sent_tasks: SentTasks, fast: None
) -> None:
    """The real object job: its object deleted while the job waited → failed NotFound with
    its event, not stuck running."""
    from workers import objects as object_job

    object_id, job_id = make_object_job(session_factory)
    with session_factory.begin() as s:
        obj = s.get(LibraryObject, object_id)
        assert obj is not None
        obj.deleted_at = utcnow()
    assert object_job.run(job_id) == "failed"
    with session_factory.begin() as s:
        job = jobs.get(s, job_id)
        assert job.state == JobState.failed and job.error_code == "NotFound"
        assert events_of(s, job_id) == [EventType.job_failed]


def test_cancel_while_running_cancels_the_subject(
    session_factory: sessionmaker[Session], sent_tasks: SentTasks, fast: None
) -> None:
    object_id, job_id = make_object_job(session_factory)
    persisted: list[str] = []

    def compute(ctx: JobContext) -> str:
        with session_factory.begin() as s:
            assert jobs.cancel(s, job_id).state == JobState.running  # asks the worker
        ctx.progress("work", 0.5)  # reads the cancel intent and raises Cancelled
        return "model"

    assert run_job(job_id, compute, persist_marks_ready(persisted)) == "cancelled"
    assert persisted == []
    with session_factory.begin() as s:
        assert jobs.get(s, job_id).state == JobState.cancelled
        obj = s.get(LibraryObject, object_id)
        assert obj is not None and obj.state == ObjectState.cancelled
        assert events_of(s, job_id) == [EventType.job_cancelled]


def test_only_locks_and_lost_connections_are_transient() -> None:
    from sqlalchemy.exc import IntegrityError

    from workers.retry import is_transient

    def sqlite_error(text: str) -> OperationalError:
        return OperationalError("SELECT 1", {}, sqlite3.OperationalError(text))

    assert is_transient(locked())
    assert is_transient(sqlite_error("database table is locked"))
    assert not is_transient(sqlite_error("no such table: jobs"))  # a bug, not a fault
    assert not is_transient(IntegrityError("INSERT", {}, Exception("duplicate key")))
    assert not is_transient(ValueError("database is locked"))
    gone = IntegrityError("UPDATE", {}, Exception("server closed the connection"))
    gone.connection_invalidated = True
    assert is_transient(gone)
