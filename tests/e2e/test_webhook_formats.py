"""Webhook formats through the running service: the API, a cpu worker running the production
tasks with the fast fake pipeline (:mod:`tests.e2e.fake_pipeline_plugin`) and a webhooks
worker, over a private Redis and a fresh PostgreSQL. Three subscriptions, one per format,
receive the same twin changes on a loopback receiver: CloudEvents once per event, an Azure
Digital Twins JSON Patch and an Eclipse Ditto merge patch per changed instance, with their
content types, all signed as today. The patches, applied in order, give the twin the API
reports."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jsonschema
import pytest

from app.core import webhooks
from tests.app.core.ditto_schema import THING_SCHEMA
from tests.app.core.rfc_patches import apply_json_patch, apply_merge_patch
from tests.app.core.test_webhook_formats import check_adt_patch
from tests.app.core.test_webhooks import Receiver
from tests.e2e.conftest import (
    FAKE_PIPELINE,
    Processes,
    RedisServer,
    api_client,
    free_port,
    wait_until,
    worker_ready,
)
from tests.e2e.test_twin_order import CLASSES, upload

pytestmark = [pytest.mark.slow, pytest.mark.e2e, pytest.mark.postgres, pytest.mark.redis]

# the twin starts empty (seq 1 is the baseline); seq 2 adds a drill and a bowl, seq 3 moves
# the drill and removes the bowl
SCENES: list[dict[str, float]] = [{"drill": 0.2}, {"drill": 0.3, "bowl": 0.5}, {"drill": 0.4}]
FORMATS = {
    "cloudevents": ("/ce", "application/cloudevents+json; charset=utf-8"),
    "azure-digital-twins": ("/adt", "application/json-patch+json"),
    "eclipse-ditto": ("/ditto", "application/merge-patch+json"),
}


def test_three_formats_receive_the_same_change_signed(
    tmp_path: Path,
    pg_url: str,
    redis_server: RedisServer,
    processes: Callable[..., Processes],
) -> None:
    procs = processes(
        database_url=pg_url,
        broker_url=redis_server.url,
        webhook_allowed_networks='["127.0.0.0/8"]',
        webhook_timeout_s="5",
    )
    port = free_port()
    procs.api(port)
    procs.worker("cpu", "cpu", "--include", FAKE_PIPELINE)
    procs.worker("wh", "webhooks", "-P", "threads")
    receiver = Receiver().start()
    try:
        client = api_client(port)
        for name in ("cpu", "wh"):
            log = tmp_path / f"{name}.log"
            wait_until(lambda log=log: worker_ready(log), 120, f"worker {name}")
        subs: dict[str, dict[str, Any]] = {}
        for fmt, (path, _) in FORMATS.items():
            r = client.post(
                "/v1/webhooks",
                json={"url": receiver.url(path), "format": fmt, "event_types": ["twin.updated"]},
            )
            assert r.status_code == 201, r.text
            subs[fmt] = r.json()
        r = client.post("/v1/environments", json={"name": "cell-3", "classes": CLASSES})
        assert r.status_code == 201, r.text
        env_id = r.json()["id"]
        for seq, scene in enumerate(SCENES, start=1):
            upload(client, env_id, scene, f"s{seq}-")

        def arrived() -> bool:
            counts = [len(receiver.on(path)) for path, _ in FORMATS.values()]
            return counts == [3, 4, 4]

        wait_until(arrived, 120, "3 CloudEvents and 4 patches of each adapter", every_s=0.5)

        hits = {fmt: receiver.on(path) for fmt, (path, _) in FORMATS.items()}
        for fmt, (_, content_type) in FORMATS.items():
            for hit in hits[fmt]:
                assert hit.headers["content-type"] == content_type
                webhooks.verify_signature(subs[fmt]["secret"], hit.headers, hit.body)
        ce = [json.loads(h.body) for h in hits["cloudevents"]]
        assert [e["data"]["outcome"] for e in ce] == ["baseline", "applied", "applied"]
        update_ids = [e["id"] for e in ce[1:]]

        twins: dict[str, Any] = {}
        for hit in hits["azure-digital-twins"]:
            twin_id, patch = hit.headers["twindelta-twin-id"], json.loads(hit.body)
            check_adt_patch(twin_id, patch)  # the official SDK takes it as it is
            empty = {"$dtId": twin_id, "$metadata": {"$model": webhooks.ADT_MODEL_ID}}
            twins[twin_id] = apply_json_patch(twins.get(twin_id, empty), patch)
        adt_events = [h.headers["webhook-id"].split(":")[0] for h in hits["azure-digital-twins"]]
        assert adt_events == [update_ids[0]] * 2 + [update_ids[1]] * 2  # in event order

        things: dict[str, Any] = {}
        for hit in hits["eclipse-ditto"]:
            thing_id, patch = hit.headers["twindelta-thing-id"], json.loads(hit.body)
            start = things.get(thing_id, {"thingId": thing_id, "policyId": thing_id})
            things[thing_id] = apply_merge_patch(start, patch)
            jsonschema.Draft202012Validator(THING_SCHEMA).validate(things[thing_id])

        # both platforms end with the twin the API reports, and the bowl marked gone
        state = client.get(f"/v1/environments/{env_id}/state").json()
        [drill] = state["objects"]
        assert drill["object"] == "drill"
        adt_drill, ditto_drill = (
            twins[drill["instance_id"]],
            things[f"twindelta:{drill['instance_id']}"],
        )
        assert adt_drill["present"] is True and adt_drill["changeType"] == "moved"
        assert adt_drill["pose"]["matrix"] == [v for row in drill["pose"] for v in row]
        assert ditto_drill["features"]["pose"]["properties"]["envFromObject"] == drill["pose"]
        [bowl_id] = set(twins) - {drill["instance_id"]}
        assert twins[bowl_id]["present"] is False and twins[bowl_id]["objectClass"] == "bowl"
        bowl_thing = things[f"twindelta:{bowl_id}"]
        assert bowl_thing["attributes"]["present"] is False and "pose" not in bowl_thing["features"]
    finally:
        receiver.stop()
