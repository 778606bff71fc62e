"""Platform adapter formats, in this process: the real twin (uploads through the API, the
production job glue with the fake pipeline) updates an environment over three snapshots, and
subscriptions of the three formats receive, on a real loopback receiver, their bodies for
the same changes, signed as CloudEvents deliveries are.

The bodies are then checked against the platforms' published shapes: each Azure Digital
Twins patch goes through the official SDK (``azure-digitaltwins-core``'s
``DigitalTwinsClient.update_digital_twin`` with a transport that captures the request), is
validated as an RFC 6902 document, conforms to the DTDL interface in ``docs/adt`` and is
applied with an RFC 6902 implementation to a twin; each Ditto merge patch is applied with an
RFC 7396 implementation to a thing, which then validates against Ditto's thing schema."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from datetime import datetime
from pathlib import Path
from typing import Any

import jsonschema
import pytest
from alembic import command
from alembic.config import Config
from azure.core.credentials import AccessToken
from azure.core.pipeline.transport import HttpResponse, HttpTransport
from azure.core.utils import case_insensitive_dict
from azure.digitaltwins.core import DigitalTwinsClient
from fastapi.testclient import TestClient
from sqlalchemy import select, text
from sqlalchemy.orm import Session, sessionmaker

from app.core import webhooks
from app.core.db import make_engine
from app.core.enums import ChangeType, EventType
from app.core.models import Delivery, Event, WebhookSubscription, new_id, utcnow
from app.core.settings import get_settings
from tests.app.conftest import Keys, SentTasks
from tests.app.core.ditto_schema import THING_SCHEMA
from tests.app.core.rfc_patches import JSON_PATCH_SCHEMA, apply_json_patch, apply_merge_patch
from tests.app.core.test_twin import Chain, apply, change, pose_at
from tests.app.core.test_twin import chain as chain  # the fixture
from tests.app.core.test_twin_order import (
    make_env,
    run_comparisons_newest_first,
    snapshot_job,
    upload,
)
from tests.app.core.test_webhooks import Hit, Receiver, drive
from tests.conftest import REPO_ROOT
from tests.workers import fake_pipeline
from workers import snapshot as snapshot_glue

# class → the fake pose's x (metres): seq 2 adds a drill and a bowl (the twin starts empty at
# the seq-1 baseline), seq 3 moves the drill and removes the bowl
SCENES: list[dict[str, float]] = [{"drill": 0.2}, {"drill": 0.3, "bowl": 0.5}, {"drill": 0.4}]
PATHS = {"cloudevents": "/ce", "azure-digital-twins": "/adt", "eclipse-ditto": "/ditto"}
INTERFACE = json.loads((REPO_ROOT / "docs" / "adt" / "TwinInstance.json").read_text())


@pytest.fixture(autouse=True)
def fake(monkeypatch: pytest.MonkeyPatch) -> None:
    fake_pipeline.install(monkeypatch.setattr)


@pytest.fixture
def loopback(data_dir: Any, monkeypatch: pytest.MonkeyPatch) -> Iterator[Receiver]:
    monkeypatch.setenv("TWINDELTA_WEBHOOK_RETRY_SCHEDULE_S", "[0.2, 0.2, 0.2]")
    monkeypatch.setenv("TWINDELTA_WEBHOOK_ALLOWED_NETWORKS", '["127.0.0.0/8"]')
    monkeypatch.setenv("TWINDELTA_WEBHOOK_TIMEOUT_S", "3")
    get_settings.cache_clear()
    receiver = Receiver().start()
    yield receiver
    receiver.stop()


def subscribe(client: TestClient, keys: Keys, url: str, fmt: str) -> dict[str, Any]:
    body: dict[str, Any] = {"url": url, "format": fmt}
    if fmt == "cloudevents":
        body["event_types"] = ["twin.updated"]
    r = client.post("/v1/webhooks", json=body, headers=keys.headers())
    assert r.status_code == 201, r.text
    made: dict[str, Any] = r.json()
    assert made["format"] == fmt and made["event_types"] == ["twin.updated"]
    return made


def run_twin(client: TestClient, keys: Keys, factory: sessionmaker[Session]) -> str:
    env_id = make_env(client, keys)
    snaps = [upload(client, keys, env_id, scene) for scene in SCENES]
    for snap_id in snaps:
        assert snapshot_glue.run(snapshot_job(factory, snap_id)) == "succeeded"
    assert run_comparisons_newest_first(factory) == [2, 3]
    return env_id


def twin_updates(factory: sessionmaker[Session], env_id: str) -> list[Event]:
    with factory() as s:
        query = select(Event).where(Event.environment_id == env_id, Event.type == "twin.updated")
        return list(s.scalars(query.order_by(Event.created_at)))


class FakeCredential:
    def get_token(self, *_scopes: str, **_kwargs: Any) -> AccessToken:
        return AccessToken("fake-token", int(time.time()) + 3600)


class NoContent(HttpResponse):
    """What Update DigitalTwin answers: 204."""

    def __init__(self, request: Any) -> None:
        super().__init__(request, None)
        self.status_code, self.reason, self.content_type = 204, "No Content", None
        self.headers = case_insensitive_dict({})

    def body(self) -> bytes:
        return b""


class CapturingTransport(HttpTransport):
    """An azure-core transport that keeps each request and answers 204."""

    def __init__(self) -> None:
        self.requests: list[Any] = []

    def __enter__(self) -> CapturingTransport:
        return self

    def __exit__(self, *_args: object) -> None:
        pass

    def open(self) -> None:
        pass

    def close(self) -> None:
        pass

    def send(self, request: Any, **_kwargs: Any) -> NoContent:
        self.requests.append(request)
        return NoContent(request)


def request_body(request: Any) -> Any:
    content = request.content
    raw = content.getvalue() if hasattr(content, "getvalue") else content
    return json.loads(raw)


def through_adt_sdk(twin_id: str, patch: list[dict[str, Any]]) -> Any:
    """Send ``patch`` with the official SDK; returns the HTTP request it made."""
    transport = CapturingTransport()
    client = DigitalTwinsClient(
        "https://twins.api.weu.digitaltwins.azure.net", FakeCredential(), transport=transport
    )
    assert client.update_digital_twin(twin_id, patch) is None  # 204 accepted
    [request] = transport.requests
    return request


def conforms(value: Any, schema: Any) -> bool:
    """``value`` is a valid DTDL v3 value of ``schema`` (the subset the interface uses)."""
    primitive = {
        "string": lambda v: isinstance(v, str),
        "boolean": lambda v: isinstance(v, bool),
        "integer": lambda v: isinstance(v, int) and not isinstance(v, bool),
        "double": lambda v: isinstance(v, int | float) and not isinstance(v, bool),
        "dateTime": lambda v: isinstance(v, str) and datetime.fromisoformat(v) is not None,
    }
    if isinstance(schema, str):
        return bool(primitive[schema](value))
    kind = schema["@type"]
    if kind == "Enum":
        return value in {e["enumValue"] for e in schema["enumValues"]}
    if kind == "Array":
        return isinstance(value, list) and all(conforms(v, schema["elementSchema"]) for v in value)
    if kind == "Object":
        fields = {f["name"]: f["schema"] for f in schema["fields"]}
        return isinstance(value, dict) and all(
            k in fields and conforms(v, fields[k]) for k, v in value.items()
        )
    raise AssertionError(f"schema {kind} not used by the interface")


def check_adt_patch(twin_id: str, patch: list[dict[str, Any]]) -> None:
    jsonschema.Draft202012Validator(JSON_PATCH_SCHEMA).validate(patch)
    properties = {c["name"]: c["schema"] for c in INTERFACE["contents"]}
    for op in patch:
        name = op["path"].removeprefix("/")
        assert op["op"] == "add" and name in properties, op
        assert conforms(op["value"], properties[name]), op
    request = through_adt_sdk(twin_id, patch)
    assert request.method == "PATCH"
    assert request.url.split("?")[0].endswith(f"/digitaltwins/{twin_id}")
    assert request.headers["Content-Type"] == "application/json-patch+json"
    assert request_body(request) == patch


def verified_hits(receiver: Receiver, path: str, secret: str) -> list[Hit]:
    hits = receiver.on(path)
    for hit in hits:
        webhooks.verify_signature(secret, hit.headers, hit.body)
    return hits


def test_three_formats_receive_their_bodies_for_the_same_twin_changes(
    client: TestClient,
    keys: Keys,
    session_factory: sessionmaker[Session],
    sent_tasks: SentTasks,
    loopback: Receiver,
) -> None:
    subs = {fmt: subscribe(client, keys, loopback.url(path), fmt) for fmt, path in PATHS.items()}
    env_id = run_twin(client, keys, session_factory)
    drive(session_factory, sent_tasks)
    baseline, second, third = twin_updates(session_factory, env_id)
    assert [e.data["outcome"] for e in (baseline, second, third)] == [
        "baseline",
        "applied",
        "applied",
    ]

    # CloudEvents: one body per event, unchanged apart from its dataschema
    ce = verified_hits(loopback, "/ce", subs["cloudevents"]["secret"])
    assert [h.headers["webhook-id"] for h in ce] == [baseline.id, second.id, third.id]
    assert {h.headers["content-type"] for h in ce} == {
        "application/cloudevents+json; charset=utf-8"
    }
    assert [h.event["data"]["seq"] for h in ce] == [1, 2, 3]
    assert ce[0].event["dataschema"] == "urn:twindelta:events:1#/$defs/twin.updated"

    # ADT: one JSON Patch per changed instance, in event order, each addressed to its twin
    adt = verified_hits(loopback, "/adt", subs["azure-digital-twins"]["secret"])
    assert len(adt) == 4  # seq 2: drill and bowl added; seq 3: drill moved, bowl removed
    assert {h.headers["content-type"] for h in adt} == {"application/json-patch+json"}
    twins: dict[str, dict[str, Any]] = {}
    for hit in adt:
        twin_id = hit.headers["twindelta-twin-id"]
        event_id = hit.headers["webhook-id"].split(":")[0]
        assert hit.headers["webhook-id"] == f"{event_id}:{twin_id}" == hit.headers["ce-id"]
        assert hit.headers["ce-type"] == "twin.updated"
        assert hit.headers["ce-subject"] == f"objects/{twin_id}"
        patch = json.loads(hit.body)
        check_adt_patch(twin_id, patch)
        empty = {"$dtId": twin_id, "$metadata": {"$model": webhooks.ADT_MODEL_ID}}
        twins[twin_id] = apply_json_patch(twins.get(twin_id, empty), patch)
    assert [h.headers["webhook-id"].split(":")[0] for h in adt] == [second.id] * 2 + [third.id] * 2
    by_class = {t["objectClass"]: t for t in twins.values()}
    drill, bowl = by_class["drill"], by_class["bowl"]
    assert drill["present"] is True and drill["changeType"] == "moved"
    assert drill["pose"]["position"]["x"] == pytest.approx(0.4) and drill["seq"] == 3
    assert drill["pose"]["matrix"][3] == pytest.approx(0.4) and len(drill["pose"]["matrix"]) == 16
    assert bowl["present"] is False and bowl["changeType"] == "removed"
    assert bowl["pose"]["position"]["x"] == pytest.approx(0.5)  # a removal leaves the last pose
    assert drill["environment"] == env_id and drill["snapshot"] == third.data["snapshot"]

    # Ditto: one merge patch per changed thing; the merged things are valid Ditto things
    ditto = verified_hits(loopback, "/ditto", subs["eclipse-ditto"]["secret"])
    assert {h.headers["content-type"] for h in ditto} == {"application/merge-patch+json"}
    things: dict[str, Any] = {}
    for hit in ditto:
        thing_id = hit.headers["twindelta-thing-id"]
        patch = json.loads(hit.body)
        assert patch["thingId"] == thing_id == f"twindelta:{hit.headers['ce-subject'][8:]}"
        start = things.get(thing_id, {"thingId": thing_id, "policyId": thing_id})
        things[thing_id] = apply_merge_patch(start, patch)
        jsonschema.Draft202012Validator(THING_SCHEMA).validate(things[thing_id])
    by_class = {t["attributes"]["objectClass"]: t for t in things.values()}
    drill_thing, bowl_thing = by_class["drill"], by_class["bowl"]
    pose = drill_thing["features"]["pose"]["properties"]
    assert pose["envFromObject"][0][3] == pytest.approx(0.4) and pose["position"]["x"] == 0.4
    assert drill_thing["attributes"]["present"] is True
    assert bowl_thing["attributes"] == {**bowl_thing["attributes"], "present": False}
    assert bowl_thing["attributes"]["changeType"] == "removed"
    assert "pose" not in bowl_thing["features"]  # deleted by the removal's null
    assert {t.removeprefix("twindelta:") for t in things} == set(twins)

    # the delivery log names the instance of each adapter delivery
    log = client.get(
        f"/v1/webhooks/{subs['azure-digital-twins']['id']}/deliveries", headers=keys.headers()
    ).json()
    assert sorted(d["instance_id"] for d in log) == sorted([*twins, *twins])
    assert {d["state"] for d in log} == {"succeeded"}
    ce_log = client.get(
        f"/v1/webhooks/{subs['cloudevents']['id']}/deliveries", headers=keys.headers()
    ).json()
    assert {d["instance_id"] for d in ce_log} == {None}


def test_a_failing_adapter_receiver_holds_its_later_patches_and_retries_them_signed(
    client: TestClient,
    keys: Keys,
    session_factory: sessionmaker[Session],
    sent_tasks: SentTasks,
    loopback: Receiver,
) -> None:
    """Patches of one subscription and environment keep their order through retries: the
    second patch is not sent while the first is failing."""
    sub = subscribe(client, keys, loopback.url("/adt"), "azure-digital-twins")
    loopback.plan("/adt", [500, 503])
    run_twin(client, keys, session_factory)
    drive(session_factory, sent_tasks)
    hits = verified_hits(loopback, "/adt", sub["secret"])
    assert [h.status for h in hits] == [500, 503, 200, 200, 200, 200]
    assert hits[0].body == hits[1].body == hits[2].body  # the same patch, retried
    assert hits[0].headers["webhook-id"] == hits[2].headers["webhook-id"]
    with session_factory() as s:
        rows = s.scalars(
            select(Delivery).where(Delivery.subscription_id == sub["id"]).order_by(Delivery.seq)
        ).all()
        assert [d.attempts for d in rows] == [3, 1, 1, 1]
        assert [json.loads(h.body) for h in hits[2:]] == [d.payload for d in rows]


def test_swapped_closes_one_twin_and_opens_another(session: Session, chain: Chain) -> None:
    """A swap is the replaced instance's removal and the new instance's arrival, both with
    change type swapped; neither needs an event of its own."""
    drill, bowl, mug = new_id(), new_id(), new_id()
    apply(
        session,
        chain,
        2,
        [
            change(ChangeType.added, "drill", drill, pose=pose_at(0.1)),
            change(ChangeType.added, "bowl", bowl, pose=pose_at(0.5)),
        ],
    )
    quality = {"verified": True, "fitness": 0.9}
    apply(
        session,
        chain,
        3,
        [
            change(
                ChangeType.swapped,
                "mug",
                mug,
                pose=pose_at(0.6),
                replaced_instance_id=bowl,
                pose_quality=quality,
            )
        ],
    )
    event = Event(
        type=EventType.twin_updated,
        environment_id=chain.env_id,
        data={
            "outcome": "applied",
            "seq": 3,
            "snapshot": chain.snapshot_ids[2],
            "comparison": chain.comparison_ids[1],
        },
        created_at=utcnow(),
    )
    changes = {c.instance_id: c for c in webhooks.instance_changes(session, event)}
    assert set(changes) == {bowl, mug}
    old, new = changes[bowl], changes[mug]
    assert (old.change_type, old.present, old.pose) == ("swapped", False, None)
    assert (new.change_type, new.present, new.pose) == ("swapped", True, pose_at(0.6))
    assert new.pose_verified is True and old.pose_verified is None
    assert all(op["path"] != "/pose" for op in webhooks.adt_patch(old))
    assert {"op": "add", "path": "/poseVerified", "value": True} in webhooks.adt_patch(new)
    assert webhooks.ditto_merge_patch(old)["features"] == {"pose": None}
    assert webhooks.ditto_merge_patch(new)["features"]["pose"]["properties"]["verified"] is True
    for c in (old, new):
        check_adt_patch(c.instance_id, webhooks.adt_patch(c))
    # other events and outcomes change no instance
    for data in ({**event.data, "outcome": "skipped"}, {**event.data, "comparison": None}):
        other = Event(type=EventType.twin_updated, data=data, created_at=utcnow())
        assert webhooks.instance_changes(session, other) == []
    blocked = Event(type=EventType.twin_blocked, data=event.data, created_at=utcnow())
    assert webhooks.instance_changes(session, blocked) == []


def test_existing_subscriptions_become_cloudevents(tmp_path: Path) -> None:
    """Migration 0006 on SQLite: rows made before it get format cloudevents; down and up
    again keeps them."""
    url = f"sqlite:///{tmp_path / 'formats.db'}"
    config = Config(str(REPO_ROOT / "alembic.ini"))
    config.attributes["url"] = url
    command.upgrade(config, "0005")
    engine = make_engine(url)
    with engine.begin() as conn:
        conn.execute(
            text(
                "INSERT INTO webhook_subscriptions (id, url, secret_encrypted, event_types,"
                " active, created_at) VALUES ('s1', 'https://example.com/h', 'x', '[]', 1,"
                " '2026-11-24 00:00:00')"
            )
        )
    command.upgrade(config, "0006")
    with Session(engine) as s:
        sub = s.get(WebhookSubscription, "s1")
        assert sub is not None and sub.format == "cloudevents"
    command.downgrade(config, "0005")
    command.upgrade(config, "0006")
    with engine.connect() as conn:
        assert conn.execute(text("SELECT format FROM webhook_subscriptions")).scalar() == (
            "cloudevents"
        )
    engine.dispose()


def readme_block(after: str) -> Any:
    """The first JSON code block after the line ``after`` in the README."""
    text = (REPO_ROOT / "README.md").read_text()
    rest = text[text.index(after) :]
    start = rest.index("```json\n") + len("```json\n")
    return json.loads(rest[start : rest.index("```", start)])


def test_the_readme_examples_are_what_the_adapters_send() -> None:
    moved = webhooks.InstanceChange(
        instance_id="3f2c9a4e-0b7d-4e51-9c1a-6d2f8e7b1a90",
        environment_id="0f8e5a1c-...",
        object_class="power_drill",
        library_object_id="a41b...",
        change_type="moved",
        present=True,
        pose=[[0.0, -1.0, 0.0, 0.42], [1.0, 0.0, 0.0, 1.07], [0, 0, 1.0, 0], [0, 0, 0, 1.0]],
        pose_verified=True,
        snapshot_id="9c1d...",
        seq=7,
        comparison_id="7a1d...",
        changed_at=datetime.fromisoformat("2026-11-24T05:08:53.144175+00:00"),
    )
    assert readme_block("A moved drill:") == webhooks.adt_patch(moved)
    assert readme_block("The moved drill:") == webhooks.ditto_merge_patch(moved)
