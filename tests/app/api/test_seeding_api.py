"""Seeding the twin through the API with the platform's own ids, then the twin's own chain
(production glue, fake pipeline) moving and removing the seeded instances: the external id
is in the state, the history, the comparisons, the events, the three webhook formats and the
glTF scene. And every refusal: 422 naming the row, nothing written."""

from __future__ import annotations

import json
from typing import Any

import jsonschema
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from app.core import seeding, webhooks
from app.core.eventschema import event_schema
from app.core.models import Event, LibraryObject
from app.core.webhooks.payload import cloudevent
from tests.app.conftest import Keys, SentTasks
from tests.app.core.ditto_schema import THING_SCHEMA
from tests.app.core.export.test_gltf import gltf_json
from tests.app.core.rfc_patches import apply_merge_patch
from tests.app.core.test_event_schema import closed
from tests.app.core.test_twin import pose_at
from tests.app.core.test_twin_order import make_env, run_comparisons_newest_first, upload
from tests.app.core.test_webhook_formats import (
    PATHS,
    check_adt_patch,
    loopback,
    snapshot_job,
    subscribe,
    verified_hits,
)
from tests.app.core.test_webhooks import Receiver, drive
from tests.workers import fake_pipeline
from workers import snapshot as snapshot_glue

__all__ = ["loopback"]  # the fixture, imported for these tests

# class → the fake pose's x (metres): the drill moves at seq 2 and 3, the bowl goes at seq 3
SCENES: list[dict[str, float]] = [
    {"drill": 0.2, "bowl": 0.5},
    {"drill": 0.3, "bowl": 0.5},
    {"drill": 0.4},
]
DRILL, BOWL = "plant-7.cell-2.drill", "plant-7.cell-2.bowl"


@pytest.fixture(autouse=True)
def fake(monkeypatch: pytest.MonkeyPatch) -> None:
    fake_pipeline.install(monkeypatch.setattr)


def objects_url(env_id: str, rest: str = "") -> str:
    return f"/v1/environments/{env_id}/objects{rest}"


def events(factory: sessionmaker[Session], env_id: str, kind: str) -> list[Event]:
    with factory() as s:
        query = select(Event).where(Event.environment_id == env_id, Event.type == kind)
        return list(s.scalars(query.order_by(Event.created_at)))


def test_seeded_instances_keep_their_platform_ids_through_the_twin_and_its_webhooks(
    client: TestClient,
    keys: Keys,
    session_factory: sessionmaker[Session],
    sent_tasks: SentTasks,
    loopback: Receiver,
) -> None:
    subs = {fmt: subscribe(client, keys, loopback.url(path), fmt) for fmt, path in PATHS.items()}
    env_id = make_env(client, keys)
    snaps = [upload(client, keys, env_id, scene) for scene in SCENES]
    assert snapshot_glue.run(snapshot_job(session_factory, snaps[0])) == "succeeded"  # baseline
    r = client.post(
        objects_url(env_id, "/import"),
        json=[
            {"object": "drill", "pose": pose_at(0.2), "external_id": DRILL},
            {"object": "bowl", "pose": pose_at(0.5), "external_id": BOWL},
        ],
        headers=keys.headers(),
    )
    assert r.status_code == 201, r.text
    drill_id, bowl_id = (o["instance_id"] for o in r.json())
    assert [(o["external_id"], o["created_snapshot"]) for o in r.json()] == [
        (DRILL, snaps[0]),
        (BOWL, snaps[0]),
    ]
    for snap_id in snaps[1:]:
        assert snapshot_glue.run(snapshot_job(session_factory, snap_id)) == "succeeded"
    assert run_comparisons_newest_first(session_factory) == [2, 3]

    read = keys.headers("read")
    state = client.get(f"/v1/environments/{env_id}/state", headers=read).json()
    assert [(o["instance_id"], o["external_id"], o["pose"][0][3]) for o in state["objects"]] == [
        (drill_id, DRILL, 0.4)
    ]
    history = client.get(objects_url(env_id, f"/{drill_id}/history"), headers=read).json()
    assert history["external_id"] == DRILL
    assert [(p["change_type"], p["snapshot"]) for p in history["poses"]] == [
        ("seeded", snaps[0]),
        ("moved", snaps[1]),
        ("moved", snaps[2]),
    ]
    bowl = client.get(objects_url(env_id, f"/{bowl_id}/history"), headers=read).json()
    assert bowl["closed_snapshot"] == snaps[2]
    comps = client.get(f"/v1/environments/{env_id}/comparisons", headers=read).json()
    matched = {(c["type"], c["instance_id"], c["external_id"]) for x in comps for c in x["changes"]}
    assert matched == {("moved", drill_id, DRILL), ("removed", bowl_id, BOWL)}
    completed = events(session_factory, env_id, "comparison.completed")
    assert {(c["instance_id"], c["external_id"]) for e in completed for c in e.data["changes"]} == {
        (drill_id, DRILL),
        (bowl_id, BOWL),
    }
    updated = events(session_factory, env_id, "twin.updated")
    moved = {"instance_id": drill_id, "external_id": DRILL, "change_type": "moved"}
    removed = {"instance_id": bowl_id, "external_id": BOWL, "change_type": "removed"}
    assert [e.data.get("instances") for e in updated] == [
        [],  # the baseline lists the instances its inventory made: none (no inventory- marker)
        [{**moved, "present": True}],
        [{**removed, "present": False}, {**moved, "present": True}],  # in the order applied
    ]

    drive(session_factory, sent_tasks)
    ce = verified_hits(loopback, "/ce", subs["cloudevents"]["secret"])
    assert [h.event for h in ce] == [json.loads(json.dumps(cloudevent(e))) for e in updated]
    assert ce[2].event["data"]["instances"][1]["external_id"] == DRILL
    strict = jsonschema.Draft202012Validator(closed(event_schema()))
    for body in [h.event for h in ce] + [cloudevent(e) for e in completed]:
        strict.validate(body)  # external ids are described: the schema is closed here
    adt = verified_hits(loopback, "/adt", subs["azure-digital-twins"]["secret"])
    assert [h.headers["twindelta-twin-id"] for h in adt] == [DRILL, BOWL, DRILL]
    for hit in adt:
        check_adt_patch(hit.headers["twindelta-twin-id"], json.loads(hit.body))
        assert hit.headers["ce-subject"] in {f"objects/{drill_id}", f"objects/{bowl_id}"}
    ditto = verified_hits(loopback, "/ditto", subs["eclipse-ditto"]["secret"])
    things: dict[str, Any] = {}
    for hit in ditto:
        patch = json.loads(hit.body)
        assert patch["thingId"] == hit.headers["twindelta-thing-id"]
        start = things.get(patch["thingId"], {"thingId": patch["thingId"], "policyId": "p:p"})
        things[patch["thingId"]] = apply_merge_patch(start, patch)
        jsonschema.Draft202012Validator(THING_SCHEMA).validate(things[patch["thingId"]])
    assert {k: t["attributes"]["externalId"] for k, t in things.items()} == {
        f"twindelta:{DRILL}": DRILL,
        f"twindelta:{BOWL}": BOWL,
    }
    glb = client.get(f"/v1/environments/{env_id}/state?format=glb", headers=read)
    nodes = [n for n in gltf_json(glb.content)["nodes"] if n.get("extras", {}).get("instance_id")]
    assert [(n["name"], n["extras"]["external_id"]) for n in nodes] == [(f"drill/{DRILL}", DRILL)]


def test_one_instance_is_created_corrected_and_retired(
    client: TestClient, keys: Keys, session_factory: sessionmaker[Session]
) -> None:
    env_id = make_env(client, keys)
    with session_factory.begin() as s:
        mug = LibraryObject(name="mug", filename="m.ply", file_key="k", size_bytes=1)
        s.add(mug)
    admin = keys.headers()
    r = client.post(
        objects_url(env_id),
        json={"object": mug.id, "pose": pose_at(0.7), "external_id": "M-1"},
        headers=admin,
    )
    assert r.status_code == 201, r.text
    made = r.json()
    assert (made["object"], made["object_id"], made["external_id"]) == ("mug", mug.id, "M-1")
    assert (made["created_snapshot"], made["since_snapshot"]) == (None, None)
    url = objects_url(env_id, f"/{made['instance_id']}")

    r = client.patch(url, json={"pose": pose_at(0.8), "external_id": "M-2"}, headers=admin)
    assert r.status_code == 200, r.text
    assert (r.json()["pose"][0][3], r.json()["external_id"], r.json()["object"]) == (
        0.8,
        "M-2",
        "mug",
    )
    r = client.patch(url, json={"external_id": None}, headers=admin)
    assert r.status_code == 200 and r.json()["external_id"] is None
    assert r.json()["pose"][0][3] == 0.8  # left out: unchanged
    for body, problem in [
        ({}, "give at least one of"),
        ({"pose": None}, "cannot be null"),
        ({"object": "hammer"}, "unknown class 'hammer'"),
        ({"pose": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}, "4×4"),
    ]:
        r = client.patch(url, json=body, headers=admin)
        assert r.status_code == 422 and problem in r.json()["detail"], (body, r.text)
    history = client.get(f"{url}/history", headers=keys.headers("read")).json()
    assert [p["change_type"] for p in history["poses"]] == ["seeded", "corrected", "corrected"]

    assert client.delete(url, headers=admin).status_code == 204
    # seeded before the twin reflected any snapshot: it never stood in a state; gone
    assert client.get(f"{url}/history", headers=admin).status_code == 404
    assert client.patch(url, json={"external_id": "x"}, headers=admin).status_code == 404


def ten_rows() -> list[dict[str, Any]]:
    return [
        {"object": "mug", "pose": pose_at(0.1 * i), "external_id": f"mug-{i}"} for i in range(10)
    ]


@pytest.mark.parametrize(
    ("row", "problem"),
    [
        ({"object": "hammer", "pose": pose_at(0)}, "row 7: unknown class 'hammer'"),
        (
            {"object": "mug", "pose": [[2.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]},
            "row 7: pose is not rigid",
        ),
        ({"object": "mug", "pose": [[1.0, 0, 0, 0], [0, 1, 0, 0]]}, "row 7: pose must be a 4×4"),
        ({"object": "mug", "pose": "identity"}, "row 7: pose: Input should be a valid array"),
        ({"object": "mug", "pose": pose_at(0), "external_id": "mug-3"}, "row 7: external_id"),
        ({"object": "mug", "pose": pose_at(0), "external_id": "held"}, "held by open instance"),
    ],
)
def test_an_import_with_a_bad_row_7_of_10_is_refused_whole(
    client: TestClient, keys: Keys, row: dict[str, Any], problem: str
) -> None:
    env_id = make_env(client, keys)
    held = {"object": "drill", "pose": pose_at(0), "external_id": "held"}
    assert client.post(objects_url(env_id), json=held, headers=keys.headers()).status_code == 201
    rows = ten_rows()
    rows[7] = row
    r = client.post(objects_url(env_id, "/import"), json=rows, headers=keys.headers())
    assert r.status_code == 422, r.text
    assert r.json()["error"] == "InvalidInput" and problem in r.json()["detail"], r.text
    state = client.get(f"/v1/environments/{env_id}/state", headers=keys.headers("read")).json()
    assert [o["external_id"] for o in state["objects"]] == ["held"]


def test_nan_in_a_pose_is_refused_naming_its_row(client: TestClient, keys: Keys) -> None:
    env_id = make_env(client, keys)
    body = json.dumps(ten_rows()).replace("0.7000000000000001", "NaN", 1)
    assert "NaN" in body
    r = client.post(
        objects_url(env_id, "/import"),
        content=body,
        headers={**keys.headers(), "Content-Type": "application/json"},
    )
    assert r.status_code == 422, r.text
    assert "[7]" in r.json()["detail"] and "pose" in r.json()["detail"], r.text


def test_only_admin_keys_seed(client: TestClient, keys: Keys) -> None:
    env_id = make_env(client, keys)
    body = {"object": "mug", "pose": pose_at(0)}
    for which in ("read", "capture"):
        r = client.post(objects_url(env_id), json=body, headers=keys.headers(which))
        assert r.status_code == 403, (which, r.text)
    r = client.post(objects_url("no-such-env"), json=body, headers=keys.headers())
    assert r.status_code == 404
    r = client.post(objects_url(env_id, "/import"), json=[], headers=keys.headers())
    assert r.status_code == 422


@pytest.mark.parametrize(
    ("twin_id", "thing_id"),
    [
        ("3f2c9a4e-0b7d-4e51-9c1a-6d2f8e7b1a90", "twindelta:3f2c9a4e-0b7d-4e51-9c1a-6d2f8e7b1a90"),
        ("site/hall 2/drill#1", "twindelta:site%2Fhall%202%2Fdrill%231"),
        ("$special", "twindelta:%24special"),
        ("Bohrmaschine-Größe", "twindelta:Bohrmaschine-Gr%C3%B6%C3%9Fe"),
        ("100%", "twindelta:100%25"),
    ],
)
def test_ditto_thing_ids_of_any_external_id_are_valid_ditto_ids(
    twin_id: str, thing_id: str
) -> None:
    got = webhooks.ditto_thing_id(twin_id)
    assert got == thing_id
    jsonschema.validate(got, THING_SCHEMA["properties"]["thingId"])


def csv_body(rows: list[dict[str, Any]], bom: bool = False) -> bytes:
    """``rows`` as a CSV import with an extra ``note`` column the import ignores."""
    columns = ["object", "external_id", *seeding.CSV_POSE_COLUMNS, "note"]
    lines = [",".join(columns)]
    for row in rows:
        cells = [str(v) for line in row["pose"] for v in line]
        lines.append(",".join([row["object"], row.get("external_id") or "", *cells, "x"]))
    text = "\r\n".join(lines) + "\r\n"
    return (b"\xef\xbb\xbf" if bom else b"") + text.encode()


def post_csv(client: TestClient, keys: Keys, env_id: str, body: bytes) -> Any:
    return client.post(
        objects_url(env_id, "/import"),
        content=body,
        headers={**keys.headers(), "Content-Type": "text/csv; charset=utf-8"},
    )


def test_a_csv_import_is_the_same_rows_and_refusals(client: TestClient, keys: Keys) -> None:
    env_id = make_env(client, keys)
    rows = ten_rows()
    rows[4]["external_id"] = None
    r = post_csv(client, keys, env_id, csv_body(rows, bom=True))
    assert r.status_code == 201, r.text
    got = [(o["object"], o["external_id"], o["pose"]) for o in r.json()]
    assert got == [(row["object"], row["external_id"], row["pose"]) for row in rows]

    other = make_env_named(client, keys, "cell-8")
    bad = ten_rows()
    bad[7]["object"] = "hammer"
    r = post_csv(client, keys, other, csv_body(bad))
    assert r.status_code == 422 and "row 7: unknown class 'hammer'" in r.json()["detail"]
    text = csv_body(ten_rows()).decode().replace("0.7000000000000001", "seven", 1)
    r = post_csv(client, keys, other, text.encode())
    assert r.status_code == 422, r.text
    assert "row 7 (line 9): a pose cell is not a number" in r.json()["detail"]
    r = post_csv(client, keys, other, b"object,m00\nmug,1\n")
    assert r.status_code == 422 and "header lacks m01" in r.json()["detail"]
    r = post_csv(client, keys, other, b"object,\xff\n")
    assert r.status_code == 422 and "not UTF-8" in r.json()["detail"]
    r = post_csv(client, keys, other, csv_body([]))
    assert r.status_code == 422 and "1 to 10000 rows" in r.json()["detail"]
    r = client.post(
        objects_url(other, "/import"),
        content=b"<rows/>",
        headers={**keys.headers(), "Content-Type": "application/xml"},
    )
    assert r.status_code == 415
    state = client.get(f"/v1/environments/{other}/state", headers=keys.headers("read")).json()
    assert state["objects"] == []


def make_env_named(client: TestClient, keys: Keys, name: str) -> str:
    r = client.post(
        "/v1/environments",
        json={"name": name, "classes": ["drill", "bowl", "mug"]},
        headers=keys.headers(),
    )
    assert r.status_code == 201, r.text
    env_id: str = r.json()["id"]
    return env_id
