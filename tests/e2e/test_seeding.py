"""Seeding through the running service (PostgreSQL, a private Redis, the API and one Celery
worker with the fake pipeline of :mod:`tests.e2e.fake_pipeline_plugin`): instances imported
as CSV after the baseline snapshot, under the platform's ids, are moved and removed by the
automatic comparisons of the captures that follow."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

from tests.e2e.conftest import (
    Processes,
    RedisServer,
    fake_pipeline_service,
    wait_until,
)
from tests.e2e.test_twin_order import CLASSES, upload

pytestmark = [pytest.mark.slow, pytest.mark.e2e, pytest.mark.postgres, pytest.mark.redis]

# class → box centre x (the fake pose's x, metres): the drill moves, then the bowl goes
SCENES: list[dict[str, float]] = [
    {"drill": 0.2, "bowl": 0.5},
    {"drill": 0.3, "bowl": 0.5},
    {"drill": 0.3},
]
CSV = (
    "object,external_id,m00,m01,m02,m03,m10,m11,m12,m13,m20,m21,m22,m23,m30,m31,m32,m33\n"
    "drill,erp:4711,1,0,0,0.2,0,1,0,0,0,0,1,0,0,0,0,1\n"
    "bowl,erp:4712,1,0,0,0.5,0,1,0,0,0,0,1,0,0,0,0,1\n"
)


def test_seeded_instances_follow_the_captures_through_the_service(
    tmp_path: Path,
    pg_url: str,
    redis_server: RedisServer,
    processes: Callable[..., Processes],
) -> None:
    procs = processes(database_url=pg_url, broker_url=redis_server.url)
    client = fake_pipeline_service(procs, worker="cpu1")
    r = client.post("/v1/environments", json={"name": "cell-2", "classes": CLASSES})
    assert r.status_code == 201, r.text
    env_id = r.json()["id"]

    first = upload(client, env_id, SCENES[0], "a")
    wait_until(
        lambda: client.get(f"/v1/environments/{env_id}").json()["twin"]["seq"] == 1,
        120,
        "the baseline",
        every_s=0.3,
    )
    r = client.post(
        f"/v1/environments/{env_id}/objects/import",
        content=CSV,
        headers={"Content-Type": "text/csv"},
    )
    assert r.status_code == 201, r.text
    ids = {o["external_id"]: o["instance_id"] for o in r.json()}
    assert {o["created_snapshot"] for o in r.json()} == {first}

    for tag, scene in zip("bc", SCENES[1:], strict=True):
        upload(client, env_id, scene, tag)
    wait_until(
        lambda: client.get(f"/v1/environments/{env_id}").json()["twin"]["seq"] == 3,
        180,
        "both comparisons applied",
        every_s=0.5,
    )
    state = client.get(f"/v1/environments/{env_id}/state").json()
    assert [(o["instance_id"], o["external_id"], o["pose"][0][3]) for o in state["objects"]] == [
        (ids["erp:4711"], "erp:4711", 0.3)
    ]
    bowl = client.get(f"/v1/environments/{env_id}/objects/{ids['erp:4712']}/history").json()
    assert [p["change_type"] for p in bowl["poses"]] == ["seeded", "removed"]
    changes = [
        (c["type"], c["external_id"])
        for comp in client.get(f"/v1/environments/{env_id}/comparisons").json()
        for c in comp["changes"]
    ]
    assert sorted(changes) == [("moved", "erp:4711"), ("removed", "erp:4712")]
