"""The answers match the OpenAPI document in the cases a fuzzer rarely reaches on its own:
timestamps carry a timezone on SQLite too, a 405 says what is allowed, and the 409 and 400
answers the API gives are documented on the operations that give them."""

from __future__ import annotations

import io
from datetime import UTC, datetime, timedelta, timezone

from fastapi.testclient import TestClient
from sqlalchemy.orm import Session, sessionmaker

from app.core.models import Environment
from app.main import create_app
from tests.app.api.test_objects_api import PLY_CUBE
from tests.app.api.test_snapshots_upload import as_parts, capture, make_env, upload
from tests.app.conftest import Keys

DOCUMENT = create_app().openapi()


def documented(method: str, path: str) -> set[int]:
    return {int(code) for code in DOCUMENT["paths"][path][method.lower()]["responses"]}


def test_timestamps_are_rfc3339_with_utc_offset(
    client: TestClient, keys: Keys, session_factory: sessionmaker[Session]
) -> None:
    """SQLite hands back naive datetimes; the API must still say UTC (RFC 3339 date-time)."""
    env_id = make_env(client, keys)
    for path in ("/v1/environments", "/v1/keys"):
        for row in client.get(path, headers=keys.headers()).json():
            created = datetime.fromisoformat(row["created_at"])
            assert created.utcoffset() == timedelta(0), row["created_at"]
    with session_factory() as s:
        env = s.get(Environment, env_id)
        assert env is not None and env.created_at.tzinfo is not None
        # an aware time in another zone is stored as the same instant
        env.created_at = datetime(2026, 1, 1, 12, tzinfo=timezone(timedelta(hours=2)))
        s.commit()
    with session_factory() as s:
        env = s.get(Environment, env_id)
        assert env is not None
        assert env.created_at == datetime(2026, 1, 1, 10, tzinfo=UTC)
        assert env.created_at.utcoffset() == timedelta(0)


def test_405_says_what_is_allowed(client: TestClient, keys: Keys) -> None:
    r = client.put("/v1/environments", headers=keys.headers())
    assert r.status_code == 405 and r.json()["error"] == "MethodNotAllowed"
    assert set(r.headers["allow"].replace(" ", "").split(",")) == {"GET", "POST"}
    r = client.delete("/v1/jobs/some-id/cancel", headers=keys.headers())
    assert r.status_code == 405 and r.headers["allow"] == "POST"


def test_conflicts_and_bad_multipart_are_documented(client: TestClient, keys: Keys) -> None:
    env_id = make_env(client, keys)
    r = client.post("/v1/environments", json={"name": "line-1", "classes": ["a"]},
                    headers=keys.headers())  # fmt: skip
    assert r.status_code == 409 and 409 in documented("POST", "/v1/environments")

    def post_object() -> int:
        return client.post(
            "/v1/objects",
            files={"file": ("a.ply", io.BytesIO(PLY_CUBE))},
            data={"name": "drill"},
            headers=keys.headers(),
        ).status_code

    assert post_object() == 202 and post_object() == 409
    assert 409 in documented("POST", "/v1/objects")

    accepted = upload(client, keys, env_id, as_parts(capture())).json()
    snapshot_id, job_id = accepted["snapshot"]["id"], accepted["job"]["id"]
    r = client.get(f"/v1/snapshots/{snapshot_id}/pointcloud", headers=keys.headers())
    assert r.status_code == 409 and r.json()["error"] == "PointCloudNotReady"
    assert 409 in documented("GET", "/v1/snapshots/{snapshot_id}/pointcloud")

    r = client.post(
        f"/v1/environments/{env_id}/comparisons",
        json={"before": snapshot_id, "after": snapshot_id},
        headers=keys.headers(),
    )
    assert r.status_code == 409 and r.json()["error"] == "SnapshotNotReconstructed"
    assert 409 in documented("POST", "/v1/environments/{environment_id}/comparisons")

    assert client.post(f"/v1/jobs/{job_id}/cancel", headers=keys.headers()).status_code == 200
    r = client.post(f"/v1/jobs/{job_id}/cancel", headers=keys.headers())
    assert r.status_code == 409 and 409 in documented("POST", "/v1/jobs/{job_id}/cancel")

    broken = b"--xyz\r\n-3083127--xyz--\r\n"  # a part without headers (found by schemathesis)
    for path in ("/v1/objects", f"/v1/environments/{env_id}/snapshots"):
        r = client.post(
            path,
            content=broken,
            headers={**keys.headers(), "Content-Type": "multipart/form-data; boundary=xyz"},
        )
        assert r.status_code == 400 and r.json()["error"] == "BadRequest", r.text
    assert 400 in documented("POST", "/v1/objects")
    assert 400 in documented("POST", "/v1/environments/{environment_id}/snapshots")
