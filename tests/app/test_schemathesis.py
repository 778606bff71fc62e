"""Schemathesis against the app, on every operation of its OpenAPI document.

Generated requests (the document's examples, the coverage phase's boundary, negative and
undeclared-method cases, and fuzzing) are sent with a real admin key to the test database
(PostgreSQL and SQLite). Each request is sent twice when it has path parameters: as generated
(mostly unknown ids: 404s) and with the ids of a small seeded world (an environment with
markers, a library object, two reconstructed snapshots with a point cloud, a comparison, a
twin instance with its pose history, a webhook with a delivery, a spare key), so the 2xx
answers are checked on real rows too. Every answer must:

- not be a 5xx;
- have a documented status code and the documented content type;
- have a body that validates against the response schema, formats included (a timestamp
  without a timezone is not a ``date-time``);
- have the documented headers; a 405 must carry ``Allow``.

Bounded and repeatable: a fixed seed, deterministic generation, no example database, no
shrinking and a few examples per operation (about a minute for both databases here)."""

from __future__ import annotations

import base64
import io
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
import schemathesis
from fastapi.testclient import TestClient
from schemathesis.checks import (
    content_type_conformance,
    not_a_server_error,
    response_headers_conformance,
    response_schema_conformance,
    status_code_conformance,
    unsupported_method,
)
from schemathesis.generation.case import Case
from sqlalchemy.orm import Session, sessionmaker

from app.core import events
from app.core.enums import EventType, SnapshotState
from app.core.models import Change, InstancePose, Snapshot, TwinInstance, utcnow
from app.core.settings import get_settings
from app.core.storage import LocalStorage
from app.main import create_app
from tests.app.api.test_objects_api import PLY_CUBE
from tests.app.api.test_snapshots_upload import CLASSES, as_parts, capture
from tests.app.conftest import Keys, SentTasks

MAX_EXAMPLES = 30
CHECKS = [
    not_a_server_error,
    status_code_conformance,
    content_type_conformance,
    response_schema_conformance,
    response_headers_conformance,
    unsupported_method,
]
CONFIG = schemathesis.Config.from_dict(
    {
        "seed": 20261124,
        "suppress-health-check": ["all"],
        "generation": {
            "max-examples": MAX_EXAMPLES,
            "deterministic": True,
            "database": "none",
            "no-shrink": True,
        },
        "phases": {"stateful": {"enabled": False}},
        "checks": {"response_schema_conformance": {"validate-formats": True}},
    }
)
APP = create_app()
schema = schemathesis.openapi.from_asgi("/openapi.json", APP, config=CONFIG)
# A tus PATCH body (raw bytes) is sent the way application/octet-stream is.
schemathesis.serializer.alias("application/offset+octet-stream", "application/octet-stream")

EYE = np.eye(4).tolist()
PUBLIC_HOOK = "https://93.184.216.34/hooks/twin"  # an address literal: no DNS lookup


def _ok(response: Any, status: int) -> Any:
    assert response.status_code == status, response.text
    return response.json()


@pytest.fixture
def world(
    client: TestClient,
    keys: Keys,
    session_factory: sessionmaker[Session],
    sent_tasks: SentTasks,
) -> Iterator[dict[str, str]]:
    """Real rows for every kind of path parameter, by parameter name."""
    admin = keys.headers("admin")
    env = _ok(
        client.post(
            "/v1/environments",
            json={
                "name": "fuzz-line",
                "classes": CLASSES,
                "reference": {"markers": {"size": 0.15, "poses": {"0": EYE, "7": EYE}}},
            },
            headers=admin,
        ),
        201,
    )
    obj = _ok(
        client.post(
            "/v1/objects",
            files={"file": ("drill.ply", io.BytesIO(PLY_CUBE))},
            data={"name": CLASSES[0], "symmetry": '{"kind": "continuous", "axis": [0, 0, 1]}'},
            headers=admin,
        ),
        202,
    )
    uploads = [
        _ok(
            client.post(
                f"/v1/environments/{env['id']}/snapshots",
                files=as_parts(capture()),
                headers=keys.headers("capture"),
            ),
            202,
        )
        for _ in range(2)
    ]
    before, after = (u["snapshot"]["id"] for u in uploads)
    storage = LocalStorage(get_settings().resolved_storage_dir)
    with session_factory.begin() as s:
        for snapshot_id in (before, after):
            snap = s.get(Snapshot, snapshot_id)
            assert snap is not None
            key = f"snapshots/{snapshot_id}/cloud.ply"
            storage.write_bytes(key, PLY_CUBE)
            snap.state, snap.pointcloud_key = SnapshotState.reconstructed, key
            snap.reconstructed_at = utcnow()
    comparison = _ok(
        client.post(
            f"/v1/environments/{env['id']}/comparisons",
            json={"before": before, "after": after, "options": {"preset": "default"}},
            headers=admin,
        ),
        202,
    )
    hook = _ok(client.post("/v1/webhooks", json={"url": PUBLIC_HOOK}, headers=admin), 201)
    spare = _ok(
        client.post("/v1/keys", json={"name": "spare", "scopes": ["read"]}, headers=admin), 201
    )
    with session_factory.begin() as s:
        instance = TwinInstance(
            environment_id=env["id"],
            object_name=CLASSES[0],
            object_id=obj["id"],
            pose=EYE,
            pose_quality={"fitness": 0.9},
            since_snapshot_id=after,
            created_snapshot_id=after,
        )
        s.add(instance)
        s.flush()
        s.add(
            InstancePose(
                instance_id=instance.id,
                snapshot_id=after,
                comparison_id=comparison["id"],
                change_type="added",
                pose=EYE,
            )
        )
        events.record(
            s,
            EventType.comparison_completed,
            environment_id=env["id"],
            subject=f"comparisons/{comparison['id']}",
            data={"comparison": comparison["id"]},
        )
        instance_id = instance.id
        change = Change(comparison_id=comparison["id"], position=0, type="added")
        s.add(change)
        s.flush()
        change_id = change.id
    [delivery] = _ok(client.get(f"/v1/webhooks/{hook['id']}/deliveries", headers=admin), 200)
    resumable = client.post(
        "/v1/uploads",
        headers={
            **admin,
            "Tus-Resumable": "1.0.0",
            "Upload-Length": "1000",
            "Upload-Metadata": f"environment_id {base64.b64encode(env['id'].encode()).decode()},"
            f"filename {base64.b64encode(b'capture.zip').decode()}",
        },
    )
    assert resumable.status_code == 201, resumable.text
    yield {
        "environment_id": env["id"],
        "object_id": obj["id"],
        "snapshot_id": after,
        "job_id": uploads[1]["job"]["id"],
        "comparison_id": comparison["id"],
        "change_id": change_id,
        "name": "a0.jpg",  # an image of the snapshot
        "instance_id": instance_id,
        "webhook_id": hook["id"],
        "delivery_id": delivery["id"],
        "key_id": spare["id"],
        "upload_id": resumable.headers["Location"].rsplit("/", 1)[1],
    }


def test_every_operation_is_fuzzed() -> None:
    """The parametrized test below covers every path and method of the document."""
    document = APP.openapi()
    declared = {
        (method.upper(), path)
        for path, item in document["paths"].items()
        for method in item
        if method in {"get", "post", "put", "patch", "delete", "head", "options"}
    }
    generated = {(op.ok().method.upper(), op.ok().path) for op in schema.get_all_operations()}
    assert declared == generated and len(declared) >= 25


def test_the_world_has_an_id_for_every_path_parameter(world: dict[str, str]) -> None:
    names = {
        p["name"]
        for item in APP.openapi()["paths"].values()
        for op in item.values()
        for p in op.get("parameters", [])
        if p["in"] == "path"
    }
    assert names <= set(world), names - set(world)


@schema.parametrize()
def test_api_conforms_to_its_schema(case: Case, keys: Keys, world: dict[str, str]) -> None:
    headers = keys.headers("admin")
    case.call_and_validate(headers=headers, checks=CHECKS)
    if case.path_parameters:
        generated = dict(case.path_parameters)
        case.path_parameters = {name: world.get(name, value) for name, value in generated.items()}
        try:
            case.call_and_validate(headers=headers, checks=CHECKS)
        finally:
            case.path_parameters = generated
