"""The inventory through the service (API + worker with the fake pipeline of
:mod:`tests.e2e.fake_pipeline_plugin`, whose inventory lists each detected class at its
fake pose when the images carry the ``inventory-`` marker): the first snapshot fills the
twin with ``inventoried`` instances, a later one confirms them (same instances, no new
history), and a removal closes the instance that stood there all along."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

from tests.e2e.conftest import Processes, RedisServer, fake_pipeline_service, wait_until
from tests.e2e.test_twin_order import CLASSES, upload

pytestmark = [pytest.mark.slow, pytest.mark.e2e, pytest.mark.postgres, pytest.mark.redis]

SCENES: list[dict[str, float]] = [
    {"drill": 0.2, "bowl": 0.5},
    {"drill": 0.2, "bowl": 0.5},
    {"drill": 0.2},
]


def test_first_snapshot_fills_the_twin_and_later_ones_confirm_it(
    tmp_path: Path,
    pg_url: str,
    redis_server: RedisServer,
    processes: Callable[..., Processes],
) -> None:
    procs = processes(database_url=pg_url, broker_url=redis_server.url)
    client = fake_pipeline_service(procs, worker="cpu1")
    r = client.post("/v1/environments", json={"name": "cell-inv", "classes": CLASSES})
    assert r.status_code == 201, r.text
    env_id = r.json()["id"]

    def twin_seq() -> int:
        return int(client.get(f"/v1/environments/{env_id}").json()["twin"]["seq"])

    first = upload(client, env_id, SCENES[0], "inventory-a")
    wait_until(lambda: twin_seq() == 1, 120, "the baseline", every_s=0.3)
    state = client.get(f"/v1/environments/{env_id}/state").json()["objects"]
    ids = {o["object"]: o["instance_id"] for o in state}
    assert {(o["last_seen_snapshot"], o["seen"]) for o in state} == {(first, True)}
    assert sorted(ids) == ["bowl", "drill"]
    assert {o["object"]: o["pose"][0][3] for o in state} == {"drill": 0.2, "bowl": 0.5}
    for instance_id in ids.values():
        h = client.get(f"/v1/environments/{env_id}/objects/{instance_id}/history").json()
        assert [p["change_type"] for p in h["poses"]] == ["inventoried"]
    listed = client.get(f"/v1/snapshots/{first}/objects")
    assert listed.status_code == 200, listed.text
    assert {(o["object"], o["instance_id"], o["verified"]) for o in listed.json()} == {
        ("drill", ids["drill"], True),
        ("bowl", ids["bowl"], True),
    }

    second = upload(client, env_id, SCENES[1], "inventory-b")
    wait_until(lambda: twin_seq() == 2, 120, "the confirmation", every_s=0.3)
    state = client.get(f"/v1/environments/{env_id}/state").json()["objects"]
    assert {o["object"]: o["instance_id"] for o in state} == ids
    for instance_id in ids.values():
        h = client.get(f"/v1/environments/{env_id}/objects/{instance_id}/history").json()
        assert [p["change_type"] for p in h["poses"]] == ["inventoried"]  # no jitter records
    confirmed = client.get(f"/v1/snapshots/{second}/objects").json()
    assert {o["instance_id"] for o in confirmed} == set(ids.values())

    assert {(o["last_seen_snapshot"], o["seen"]) for o in state} == {(second, True)}

    upload(client, env_id, SCENES[2], "inventory-c")
    wait_until(lambda: twin_seq() == 3, 120, "the removal", every_s=0.3)
    state = client.get(f"/v1/environments/{env_id}/state").json()["objects"]
    assert [(o["object"], o["instance_id"]) for o in state] == [("drill", ids["drill"])]
    h = client.get(f"/v1/environments/{env_id}/objects/{ids['bowl']}/history").json()
    assert [p["change_type"] for p in h["poses"]] == ["inventoried", "removed"]
    missing = client.get("/v1/snapshots/nope/objects")
    assert missing.status_code == 404
