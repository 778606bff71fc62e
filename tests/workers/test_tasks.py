"""The maintenance.sweep task: one job that cannot be recovered (its subject deleted, or any
other error) never stops the sweeper from recovering the others."""

from __future__ import annotations

from datetime import timedelta

import pytest
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from app.core import jobs, lifecycle
from app.core.enums import EventType, JobKind, JobState, ObjectState
from app.core.models import Event, Job, LibraryObject, utcnow
from app.core.settings import get_settings
from tests.app.conftest import SentTasks
from workers.tasks import sweep


def stale_object_job(factory: sessionmaker[Session], name: str, *, attempts: int) -> str:
    """An object job whose worker died: running, heartbeat long gone."""
    settings = get_settings()
    with factory.begin() as s:
        obj = LibraryObject(name=name, filename="m.ply", file_key="k", size_bytes=1)
        s.add(obj)
        s.flush()
        job_id = jobs.create(s, JobKind.object, "object.prepare", object_id=obj.id).id
    with factory.begin() as s:
        jobs.claim(s, job_id, "dead-worker")
        job = jobs.get(s, job_id)
        job.attempts = attempts
        job.heartbeat_at = utcnow() - timedelta(seconds=settings.heartbeat_timeout_s + 60)
    return job_id


def test_a_deleted_object_does_not_poison_the_sweeper(
    session_factory: sessionmaker[Session], sent_tasks: SentTasks
) -> None:
    """Create an object and delete it at once while its job is pending: the sweeper fails
    the job (WorkerLost, job.failed) and goes on recovering every other job, every time."""
    exhausted = get_settings().max_job_attempts
    orphan = stale_object_job(session_factory, "deleted", attempts=exhausted)
    with session_factory.begin() as s:
        job = jobs.get(s, orphan)
        obj = s.get(LibraryObject, job.object_id)
        assert obj is not None
        obj.deleted_at = utcnow()
    other = stale_object_job(session_factory, "alive", attempts=1)
    sent_tasks.calls.clear()

    counts = sweep()

    assert counts["failed"] == 1 and counts["requeued"] == 1
    assert sent_tasks.calls == [("object.prepare", {"job_id": other})]
    with session_factory.begin() as s:
        gone = jobs.get(s, orphan)
        assert gone.state == JobState.failed and gone.error_code == "WorkerLost"
        assert s.scalars(select(Event.type).where(Event.subject == f"jobs/{orphan}")).all() == [
            EventType.job_failed
        ]
        assert jobs.get(s, other).state == JobState.queued
    # and the next sweep runs as well
    assert sweep()["failed"] == 0


def test_an_error_on_one_job_is_logged_and_the_rest_are_recovered(
    session_factory: sessionmaker[Session],
    sent_tasks: SentTasks,
    monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
) -> None:
    exhausted = get_settings().max_job_attempts
    broken = stale_object_job(session_factory, "broken", attempts=exhausted)
    fine = stale_object_job(session_factory, "fine", attempts=exhausted)
    real_settle = lifecycle.settle

    def settle(session: Session, job: Job) -> None:
        if job.id == broken:
            raise RuntimeError("a bug in one failure handler")
        real_settle(session, job)

    monkeypatch.setattr(lifecycle, "settle", settle)

    counts = sweep()

    assert counts["failed"] == 1 and counts["errors"] == 1
    assert f"job {broken}" in caplog.text and "a bug in one failure handler" in caplog.text
    with session_factory.begin() as s:
        assert jobs.get(s, fine).state == JobState.failed
        obj = s.get(LibraryObject, jobs.get(s, fine).object_id)
        assert obj is not None and obj.state == ObjectState.failed
        # the broken one is rolled back to its savepoint: untouched, tried again next sweep
        assert jobs.get(s, broken).state == JobState.running


def test_a_cancelled_job_whose_worker_died_ends_cancelled_with_its_subject(
    session_factory: sessionmaker[Session], sent_tasks: SentTasks
) -> None:
    job_id = stale_object_job(session_factory, "cancelled", attempts=1)
    with session_factory.begin() as s:
        jobs.cancel(s, job_id)  # asked while running; the worker died before it saw it
    assert sweep()["cancelled"] == 1
    with session_factory.begin() as s:
        job = jobs.get(s, job_id)
        assert job.state == JobState.cancelled
        obj = s.get(LibraryObject, job.object_id)
        assert obj is not None and obj.state == ObjectState.cancelled
        assert s.scalars(select(Event.type).where(Event.subject == f"jobs/{job_id}")).all() == [
            EventType.job_cancelled
        ]


def test_a_worker_sweeps_its_own_hosts_work_folders_at_start(
    session_factory: sessionmaker[Session], monkeypatch: pytest.MonkeyPatch
) -> None:
    """worker_ready: the scratch work folders of ended jobs and of jobs with no row go, a
    running job's stays; a database that is down only skips the sweep."""
    from app.core import retention
    from app.core.storage import open_storage
    from workers import maintenance_tasks

    ended = stale_object_job(session_factory, "ended", attempts=1)
    running = stale_object_job(session_factory, "running", attempts=1)
    with session_factory.begin() as s:
        jobs.get(s, ended).state = JobState.failed
    storage = open_storage(get_settings())
    folders = {
        name: storage.scratch_path(f".work/{job_id}")
        for name, job_id in (("ended", ended), ("running", running), ("unknown", "no-such-job"))
    }
    for folder in folders.values():
        (folder / "reconstruct").mkdir(parents=True)
    assert maintenance_tasks.sweep_own_scratch() == 2
    assert not folders["ended"].exists() and not folders["unknown"].exists()
    assert (folders["running"] / "reconstruct").is_dir()

    def down(*_: object) -> int:
        raise ConnectionError("database is starting")

    monkeypatch.setattr(retention, "sweep_work", down)
    assert maintenance_tasks.sweep_own_scratch() == 0
