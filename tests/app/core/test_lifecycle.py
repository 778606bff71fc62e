"""A job that ends failed or cancelled brings its subject (snapshot, comparison, object) to the
same end and records the job's event, whoever ended it: the cancel route, the runner or the
sweeper; a subject deleted meanwhile is skipped, never an error."""

from __future__ import annotations

from dataclasses import dataclass

import pytest
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from app.core import jobs, lifecycle
from app.core.enums import (
    ComparisonState,
    EventType,
    JobKind,
    JobState,
    ObjectState,
    SnapshotState,
)
from app.core.models import (
    Comparison,
    Environment,
    Event,
    Job,
    LibraryObject,
    Snapshot,
    new_id,
    utcnow,
)
from tests.app.conftest import SentTasks


@dataclass
class Subject:
    kind: str
    id: str
    job_id: str


def make_subject(s: Session, kind: str) -> Subject:
    """A subject in its working state and the queued job that works on it."""
    env = Environment(name=f"env-{new_id()[:8]}", classes=["a"])
    s.add(env)
    s.flush()
    if kind == "object":
        name = f"obj-{new_id()[:8]}"
        obj = LibraryObject(name=name, filename="m.ply", file_key="k", size_bytes=1)
        s.add(obj)
        s.flush()
        job = jobs.create(s, JobKind.object, "object.prepare", object_id=obj.id)
        return Subject(kind, obj.id, job.id)
    snaps = [
        Snapshot(environment_id=env.id, seq=seq, storage_prefix=f"p/{seq}", state=state)
        for seq, state in ((1, SnapshotState.reconstructed), (2, SnapshotState.uploaded))
    ]
    s.add_all(snaps)
    s.flush()
    if kind == "snapshot":
        job = jobs.create(
            s, JobKind.snapshot, "snapshot.process", environment_id=env.id, snapshot_id=snaps[1].id
        )
        return Subject(kind, snaps[1].id, job.id)
    comparison_id = new_id()
    job = jobs.create(
        s, JobKind.comparison, "comparison.run", environment_id=env.id, comparison_id=comparison_id
    )
    s.add(
        Comparison(
            id=comparison_id,
            environment_id=env.id,
            before_id=snaps[0].id,
            after_id=snaps[0].id,
            job_id=job.id,
        )
    )
    s.flush()
    return Subject(kind, comparison_id, job.id)


def subject_state(s: Session, subject: Subject) -> str:
    model = {"snapshot": Snapshot, "comparison": Comparison, "object": LibraryObject}
    row = s.get(model[subject.kind], subject.id)  # type: ignore[attr-defined]
    assert row is not None
    return str(row.state)


def job_events(s: Session, job_id: str) -> list[str]:
    return [str(e.type) for e in s.scalars(select(Event).where(Event.subject == f"jobs/{job_id}"))]


@pytest.mark.parametrize("kind", ["snapshot", "comparison", "object"])
def test_cancelling_a_queued_job_cancels_its_subject(
    session_factory: sessionmaker[Session], sent_tasks: SentTasks, kind: str
) -> None:
    with session_factory.begin() as s:
        subject = make_subject(s, kind)
    with session_factory.begin() as s:
        assert jobs.cancel(s, subject.job_id).state == JobState.cancelled
    with session_factory.begin() as s:
        assert subject_state(s, subject) == "cancelled"
        assert job_events(s, subject.job_id) == [EventType.job_cancelled]
        event = s.scalars(select(Event).where(Event.subject == f"jobs/{subject.job_id}")).one()
        assert event.data[kind] == subject.id and event.data["error"]["code"] == "Cancelled"


@pytest.mark.parametrize("kind", ["snapshot", "comparison", "object"])
def test_a_failed_job_fails_its_subject_and_records_job_failed(
    session_factory: sessionmaker[Session], sent_tasks: SentTasks, kind: str
) -> None:
    with session_factory.begin() as s:
        subject = make_subject(s, kind)
        attempt = jobs.claim(s, subject.job_id, "w")
        assert attempt is not None
    with session_factory.begin() as s:
        job = jobs.finish(
            s, subject.job_id, attempt, JobState.failed, error_code="X", error_detail="why"
        )
        assert job is not None
        lifecycle.settle(s, job)
    with session_factory.begin() as s:
        assert subject_state(s, subject) == "failed"
        assert job_events(s, subject.job_id) == [EventType.job_failed]
        if kind == "snapshot":
            snap = s.get(Snapshot, subject.id)
            assert snap is not None and snap.quality["error"] == {"code": "X", "detail": "why"}


def test_a_deleted_subject_is_skipped(
    session_factory: sessionmaker[Session], sent_tasks: SentTasks
) -> None:
    with session_factory.begin() as s:
        gone = make_subject(s, "object")
        obj = s.get(LibraryObject, gone.id)
        assert obj is not None
        obj.deleted_at = utcnow()  # the object was deleted while its job waited
        orphan = jobs.create(s, JobKind.comparison, "comparison.run", comparison_id=new_id())
    with session_factory.begin() as s:
        for job_id in (gone.job_id, orphan.id):
            job = jobs.cancel(s, job_id)
            assert job.state == JobState.cancelled
    with session_factory.begin() as s:
        for job_id in (gone.job_id, orphan.id):
            assert jobs.get(s, job_id).state == JobState.cancelled
            assert job_events(s, job_id) == [EventType.job_cancelled]


def test_a_finished_subject_is_never_rewritten(
    session_factory: sessionmaker[Session], sent_tasks: SentTasks
) -> None:
    """A failure reported late (the sweeper, a zombie attempt) never undoes a result."""
    with session_factory.begin() as s:
        subject = make_subject(s, "comparison")
        comparison = s.get(Comparison, subject.id)
        assert comparison is not None
        comparison.state = ComparisonState.succeeded
        done = make_subject(s, "object")
        obj = s.get(LibraryObject, done.id)
        assert obj is not None
        obj.state = ObjectState.ready
    with session_factory.begin() as s:
        for job_id in (subject.job_id, done.job_id):
            job = s.get(Job, job_id)
            assert job is not None
            job.state = JobState.failed
            lifecycle.settle(s, job)
    with session_factory.begin() as s:
        assert subject_state(s, subject) == "succeeded"
        assert subject_state(s, done) == "ready"


def test_settle_refuses_a_job_that_did_not_end_badly(
    session_factory: sessionmaker[Session], sent_tasks: SentTasks
) -> None:
    with session_factory.begin() as s:
        subject = make_subject(s, "object")
        job = jobs.get(s, subject.job_id)
        with pytest.raises(ValueError, match="queued"):
            lifecycle.settle(s, job)
