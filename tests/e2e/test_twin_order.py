"""Two CPU workers, uploads finishing out of order: the twin is still brought forward in
snapshot ``seq`` order (PostgreSQL, a private Redis, the API and two Celery worker processes).

The workers run the production tasks with the fast fake pipeline
(:mod:`tests.e2e.fake_pipeline_plugin`): the order of events is what is under test, not the
geometry. Snapshot 2 takes seconds to reconstruct, so with two workers snapshots 3 and 4
reconstruct before it."""

from __future__ import annotations

import io
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from PIL import Image

from tests.e2e.conftest import (
    FAKE_PIPELINE,
    Processes,
    RedisServer,
    api_client,
    free_port,
    wait_until,
    worker_ready,
)

pytestmark = [pytest.mark.slow, pytest.mark.e2e, pytest.mark.postgres, pytest.mark.redis]

CLASSES = ["drill", "bowl", "mug"]
# class → box centre x (the fake pose's x, metres); the twin ends with the last scene
SCENES: list[dict[str, float]] = [
    {"drill": 0.2, "bowl": 0.5},
    {"drill": 0.3, "bowl": 0.5, "mug": 0.7},
    {"drill": 0.4, "mug": 0.7},
    {"drill": 0.4, "mug": 0.8, "bowl": 0.1},
]
SLOW_S = 6  # snapshot 2's reconstruction time


def png(seed: int) -> bytes:
    pixels = np.random.default_rng(seed).integers(0, 255, (24, 32, 3), dtype=np.uint8)
    out = io.BytesIO()
    Image.fromarray(pixels).save(out, "PNG")
    return out.getvalue()


def upload(
    client: httpx.Client,
    env_id: str,
    scene: dict[str, float],
    tag: str,
    classes: list[str] = CLASSES,
) -> str:
    """A capture of three images whose YOLO boxes put each class of ``classes`` at x (the
    fake pose); returns the snapshot id."""
    labels = "".join(f"{classes.index(n)} {x} 0.5 0.1 0.1\n" for n, x in scene.items())
    files = []
    for i in range(3):
        files.append(("images", (f"{tag}{i}.png", png(i), "image/png")))
        files.append(("detections", (f"{tag}{i}.txt", labels.encode(), "text/plain")))
    r = client.post(f"/v1/environments/{env_id}/snapshots", files=files)
    assert r.status_code == 202, r.text
    snap_id: str = r.json()["snapshot"]["id"]
    return snap_id


def test_two_workers_uploads_finishing_out_of_order_twin_in_seq_order(
    tmp_path: Path,
    pg_url: str,
    redis_server: RedisServer,
    processes: Callable[..., Processes],
) -> None:
    procs = processes(database_url=pg_url, broker_url=redis_server.url)
    port = free_port()
    procs.api(port)
    for name in ("cpu1", "cpu2"):
        procs.worker(name, "cpu", "--include", FAKE_PIPELINE)
    client = api_client(port)
    for name in ("cpu1", "cpu2"):
        log = tmp_path / f"{name}.log"
        wait_until(lambda log=log: worker_ready(log), 120, f"worker {name}")
    r = client.post("/v1/environments", json={"name": "cell-9", "classes": CLASSES})
    assert r.status_code == 201, r.text
    env_id = r.json()["id"]

    snaps = [
        upload(client, env_id, scene, f"delay-{SLOW_S}-" if seq == 2 else "v")
        for seq, scene in enumerate(SCENES, start=1)
    ]

    def automatic() -> list[dict[str, Any]]:
        comps: list[dict[str, Any]] = client.get(f"/v1/environments/{env_id}/comparisons").json()
        return [c for c in comps if c["automatic"]]

    def settled() -> bool:
        comps = automatic()
        final = {"succeeded", "failed", "cancelled"}
        return len(comps) == len(SCENES) - 1 and all(c["state"] in final for c in comps)

    wait_until(settled, 180, "every automatic comparison to finish", every_s=0.5)

    got = [client.get(f"/v1/snapshots/{s}").json() for s in snaps]
    assert [s["state"] for s in got] == ["reconstructed"] * len(SCENES)
    # the uploads did finish out of order: 3 and 4 before 2
    assert got[2]["reconstructed_at"] < got[1]["reconstructed_at"]
    assert got[3]["reconstructed_at"] < got[1]["reconstructed_at"]

    state = client.get(f"/v1/environments/{env_id}/state").json()
    assert {o["object"]: o["pose"][0][3] for o in state["objects"]} == SCENES[-1]
    seq_of = {s["id"]: s["seq"] for s in got}
    comps = automatic()
    assert sorted((seq_of[c["before"]], seq_of[c["after"]]) for c in comps) == [
        (1, 2),
        (2, 3),
        (3, 4),
    ]
    applied = sorted((c["applied_at"], seq_of[c["after"]]) for c in comps)
    assert all(c["applied_to_twin"] for c in comps)
    assert [seq for _, seq in applied] == [2, 3, 4]
    mug = next(o for o in state["objects"] if o["object"] == "mug")
    history = client.get(f"/v1/environments/{env_id}/objects/{mug['instance_id']}/history")
    poses = history.json()["poses"]
    assert [seq_of[p["snapshot"]] for p in poses] == [2, 4]
    assert [p["pose"][0][3] for p in poses] == [0.7, 0.8]
    env = client.get(f"/v1/environments/{env_id}").json()
    assert env["twin"]["seq"] == 4 and env["twin"]["status"] == "current"
    assert state["twin"]["snapshot"] == snaps[-1]
