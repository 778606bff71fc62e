"""``openapi/events.schema.json``: generated from :mod:`app.core.eventschema`, fresh, served
by the API, and describing the events the service really records, every type of them.

Real events come from a real run (uploads through the API, the production job glue with the
fake pipeline): a baseline, a failed snapshot (skipped), a failed automatic comparison (the
twin blocked), its retry (changes applied), and a snapshot cancelled while queued. Each
CloudEvent body is validated against the schema with every described object closed
(``additionalProperties: false``), so a field an event gains without the schema fails here,
and its ``data`` against the ``$defs`` entry its ``dataschema`` names, resolved through the
``$id`` of the document the API serves."""

from __future__ import annotations

import copy
import json
from typing import Any

import jsonschema
import pytest
from fastapi.testclient import TestClient
from referencing import Registry, Resource
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from app.core import webhooks
from app.core.enums import EventType
from app.core.eventschema import EVENTS_SCHEMA_ID, event_schema, schema_text
from app.core.models import Event
from tests.app.conftest import Keys, SentTasks
from tests.app.core.test_twin_order import (
    SCENES,
    make_env,
    queued_comparisons,
    run_comparisons_newest_first,
    snapshot_job,
    upload,
)
from tests.conftest import REPO_ROOT
from tests.workers import fake_pipeline
from workers import comparison as comparison_glue
from workers import snapshot as snapshot_glue
from workers.pipeline.errors import PipelineError


def closed(schema: Any) -> Any:
    """``schema`` with ``additionalProperties: false`` on every object that lists its
    properties (the published schema stays open to additions)."""
    out = copy.deepcopy(schema)

    def walk(node: Any) -> None:
        if isinstance(node, dict):
            kind = node.get("type")
            is_object = kind == "object" or (isinstance(kind, list) and "object" in kind)
            if is_object and "properties" in node:
                node.setdefault("additionalProperties", False)
            for value in node.values():
                walk(value)
        elif isinstance(node, list):
            for value in node:
                walk(value)

    walk(out)
    return out


def test_the_published_file_is_fresh_and_a_valid_schema() -> None:
    path = REPO_ROOT / "openapi" / "events.schema.json"
    assert path.read_text() == schema_text(), "run: python -m app.core.eventschema > " + str(path)
    jsonschema.Draft202012Validator.check_schema(event_schema())
    assert event_schema()["$id"] == EVENTS_SCHEMA_ID
    assert set(event_schema()["$defs"]) >= {t.value for t in EventType}


def test_the_api_serves_the_schema_to_any_key(client: TestClient, keys: Keys) -> None:
    for who in ("read", "admin"):
        r = client.get("/v1/webhooks/schemas/events", headers=keys.headers(who))
        assert r.status_code == 200 and r.json() == json.loads(schema_text())
    assert client.get("/v1/webhooks/schemas/events").status_code == 401


def record_every_event_type(
    client: TestClient, keys: Keys, factory: sessionmaker[Session], monkeypatch: Any
) -> str:
    env_id = make_env(client, keys)
    first = upload(client, keys, env_id, SCENES[0])
    failing = upload(client, keys, env_id, SCENES[1], tag="fail-")
    third = upload(client, keys, env_id, SCENES[1])
    for snap_id, outcome in ((first, "succeeded"), (failing, "failed"), (third, "succeeded")):
        assert snapshot_glue.run(snapshot_job(factory, snap_id)) == outcome

    def broken(*_args: Any, **_kwargs: Any) -> Any:
        raise PipelineError("the disk went away", code="FakeFailure")

    monkeypatch.setattr(comparison_glue, "compare_snapshots", broken)
    [(_, job_id)] = queued_comparisons(factory)
    assert comparison_glue.run(job_id) == "failed"  # job.failed, twin.blocked
    comps = client.get(f"/v1/environments/{env_id}/comparisons", headers=keys.headers()).json()
    r = client.post(f"/v1/comparisons/{comps[0]['id']}/retry", headers=keys.headers())
    assert r.status_code == 202, r.text
    fake_pipeline.install(monkeypatch.setattr)
    assert run_comparisons_newest_first(factory) == [3]  # comparison.completed, applied
    cancelled = upload(client, keys, env_id, SCENES[2])
    job = snapshot_job(factory, cancelled)
    assert client.post(f"/v1/jobs/{job}/cancel", headers=keys.headers()).status_code == 200
    return env_id


def test_real_events_of_every_type_match_the_schema(
    client: TestClient,
    keys: Keys,
    session_factory: sessionmaker[Session],
    sent_tasks: SentTasks,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    fake_pipeline.install(monkeypatch.setattr)
    env_id = record_every_event_type(client, keys, session_factory, monkeypatch)
    served = client.get("/v1/webhooks/schemas/events", headers=keys.headers("read")).json()
    registry: Registry[Any] = Registry().with_resource(
        EVENTS_SCHEMA_ID, Resource.from_contents(served)
    )
    strict = jsonschema.Draft202012Validator(
        closed(served), format_checker=jsonschema.Draft202012Validator.FORMAT_CHECKER
    )
    with session_factory() as s:
        events = s.scalars(select(Event).where(Event.environment_id == env_id)).all()
        bodies = [webhooks.cloudevent(e) for e in events]
    for body in bodies:
        strict.validate(body)
        by_pointer = jsonschema.Draft202012Validator(
            {"$ref": body["dataschema"]}, registry=registry
        )
        by_pointer.validate(body["data"])
    assert {b["type"] for b in bodies} == {t.value for t in EventType}
    outcomes = {b["data"]["outcome"] for b in bodies if b["type"] == "twin.updated"}
    assert outcomes == {"baseline", "skipped", "applied"}
    jobs = {(b["type"], b["data"]["kind"]) for b in bodies if b["type"].startswith("job.")}
    assert jobs == {
        ("job.failed", "snapshot"),
        ("job.failed", "comparison"),
        ("job.cancelled", "snapshot"),
    }


def test_the_strict_schema_refuses_what_the_events_do_not_carry() -> None:
    """The closed schema is what makes the test above a freshness check: an undescribed
    member, a wrong type or a data shape of another type fail."""
    strict = jsonschema.Draft202012Validator(closed(event_schema()))
    good = {
        "specversion": "1.0",
        "id": "e1",
        "source": "/twindelta/environments/env1",
        "type": "twin.blocked",
        "time": "2026-11-24T00:00:00Z",
        "datacontenttype": "application/json",
        "dataschema": "urn:twindelta:events:1#/$defs/twin.blocked",
        "data": {
            "environment": "env1",
            "snapshot": "s2",
            "seq": 2,
            "comparison": "c1",
            "twin_seq": 1,
            "error": {"code": "FakeFailure", "detail": "x"},
            "links": {"comparison": "/v1/comparisons/c1", "retry": "/v1/comparisons/c1/retry"},
        },
    }
    strict.validate(good)
    bad_data = [
        {**good["data"], "surprise": 1},
        {**good["data"], "seq": "2"},
        {k: v for k, v in good["data"].items() if k != "error"},
    ]
    for data in bad_data:
        assert not strict.is_valid({**good, "data": data}), data
    assert not strict.is_valid({**good, "dataschema": "urn:twindelta:events:1#/$defs/job.failed"})
    assert not strict.is_valid({**good, "type": "job.failed"})  # the data is not a job's
