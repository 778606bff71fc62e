"""Polling a job: state, links, the sub-second cache, and cancel seen at once."""

from __future__ import annotations

from fastapi.testclient import TestClient
from sqlalchemy.orm import Session, sessionmaker

from app.core import jobs
from app.core.enums import JobKind
from tests.app.conftest import Keys, SentTasks


def test_poll_then_cancel_is_seen_at_once(
    client: TestClient, keys: Keys, session_factory: sessionmaker[Session], sent_tasks: SentTasks
) -> None:
    with session_factory.begin() as s:
        job_id = jobs.create(s, JobKind.object, "object.prepare").id
    first = client.get(f"/v1/jobs/{job_id}", headers=keys.headers("read"))
    assert first.status_code == 200 and first.json()["state"] == "queued"
    assert first.json()["links"]["self"] == f"/v1/jobs/{job_id}"
    # an object job belongs to no environment: cancelling it needs admin (see test_keys)
    cancelled = client.post(f"/v1/jobs/{job_id}/cancel", headers=keys.headers())
    assert cancelled.status_code == 200 and cancelled.json()["state"] == "cancelled"
    # within the cache's lifetime, the poll shows this process's cancel, not the cached read
    again = client.get(f"/v1/jobs/{job_id}", headers=keys.headers("read"))
    assert again.json()["state"] == "cancelled"
    assert client.post(f"/v1/jobs/{job_id}/cancel", headers=keys.headers()).status_code == 409
