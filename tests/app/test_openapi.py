"""openapi/openapi.json is generated from the app; a stale file fails the suite."""

from __future__ import annotations

from app.cli import openapi_json
from tests.conftest import REPO_ROOT


def test_openapi_file_is_current() -> None:
    committed = (REPO_ROOT / "openapi" / "openapi.json").read_text()
    assert committed == openapi_json(), "openapi/openapi.json is stale: run `make openapi`"


def test_every_contract_endpoint_exists() -> None:
    import json

    paths = json.loads(openapi_json())["paths"]
    expected = {
        ("post", "/v1/objects"),
        ("get", "/v1/objects"),
        ("get", "/v1/objects/{object_id}"),
        ("delete", "/v1/objects/{object_id}"),
        ("post", "/v1/environments"),
        ("get", "/v1/environments"),
        ("get", "/v1/environments/{environment_id}"),
        ("post", "/v1/environments/{environment_id}/snapshots"),
        ("get", "/v1/environments/{environment_id}/snapshots"),
        ("get", "/v1/snapshots/{snapshot_id}"),
        ("get", "/v1/snapshots/{snapshot_id}/pointcloud"),
        ("get", "/v1/jobs/{job_id}"),
        ("post", "/v1/jobs/{job_id}/cancel"),
        ("post", "/v1/environments/{environment_id}/comparisons"),
        ("get", "/v1/environments/{environment_id}/comparisons"),
        ("get", "/v1/comparisons/{comparison_id}"),
        ("get", "/v1/environments/{environment_id}/state"),
        ("get", "/v1/environments/{environment_id}/objects/{instance_id}/history"),
        ("post", "/v1/webhooks"),
        ("get", "/v1/webhooks"),
        ("get", "/v1/webhooks/{webhook_id}/deliveries"),
        ("post", "/v1/webhooks/{webhook_id}/deliveries/{delivery_id}/redeliver"),
        ("options", "/v1/uploads"),
        ("post", "/v1/uploads"),
        ("head", "/v1/uploads/{upload_id}"),
        ("patch", "/v1/uploads/{upload_id}"),
        ("delete", "/v1/uploads/{upload_id}"),
        ("get", "/v1/uploads/{upload_id}"),
        ("get", "/healthz"),
        ("get", "/readyz"),
        ("get", "/metrics"),
    }
    present = {(m, p) for p, ops in paths.items() for m in ops}
    assert expected - present == set()
