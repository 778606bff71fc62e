"""API keys over HTTP: keys limited to environments (reads, uploads, jobs, lists), cancel
needs the job's environment or admin, /metrics needs a key, the last admin key stays,
and repeated bad keys from one address get 429."""

from __future__ import annotations

import time
from dataclasses import dataclass

import pytest
from fastapi.testclient import TestClient
from sqlalchemy.orm import Session, sessionmaker

from app.core import auth, jobs
from app.core.enums import JobKind
from app.core.models import ApiKey, Comparison, Snapshot
from app.core.settings import get_settings
from tests.app.api.test_snapshots_upload import as_parts, capture
from tests.app.conftest import Keys, SentTasks


def bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def make_env(client: TestClient, keys: Keys, name: str) -> str:
    r = client.post(
        "/v1/environments",
        json={"name": name, "classes": ["power_drill", "bowl"]},
        headers=keys.headers(),
    )
    assert r.status_code == 201, r.text
    env_id: str = r.json()["id"]
    return env_id


@dataclass
class EnvRows:
    env: str
    snapshot: str
    snapshot_job: str
    comparison: str


def env_rows(session_factory: sessionmaker[Session], env_id: str) -> EnvRows:
    """A snapshot with its job and a comparison in ``env_id``, written directly."""
    with session_factory.begin() as s:
        snap = Snapshot(environment_id=env_id, seq=1, storage_prefix="snapshots/x")
        s.add(snap)
        s.flush()
        snap_job = jobs.create(
            s, JobKind.snapshot, "snapshot.process", environment_id=env_id, snapshot_id=snap.id
        )
        cmp_job = jobs.create(s, JobKind.comparison, "comparison.run", environment_id=env_id)
        comparison = Comparison(
            environment_id=env_id, before_id=snap.id, after_id=snap.id, job_id=cmp_job.id
        )
        s.add(comparison)
        s.flush()
        return EnvRows(env_id, snap.id, snap_job.id, comparison.id)


def create_key(client: TestClient, keys: Keys, **body: object) -> dict[str, object]:
    r = client.post("/v1/keys", json={"name": "k", **body}, headers=keys.headers())
    assert r.status_code == 201, r.text
    out: dict[str, object] = r.json()
    return out


def test_key_limited_to_an_environment_reaches_only_that_one(
    client: TestClient, keys: Keys, session_factory: sessionmaker[Session], sent_tasks: SentTasks
) -> None:
    own = env_rows(session_factory, make_env(client, keys, "station-1"))
    other = env_rows(session_factory, make_env(client, keys, "station-2"))
    created = create_key(client, keys, scopes=["capture", "read"], environment_ids=[own.env])
    assert created["environment_ids"] == [own.env]
    station = bearer(str(created["key"]))

    listed = client.get("/v1/environments", headers=station).json()
    assert [e["id"] for e in listed] == [own.env]
    everything = client.get("/v1/environments", headers=keys.headers("read")).json()
    assert {e["id"] for e in everything} == {own.env, other.env}

    def paths(rows: EnvRows) -> list[str]:
        return [
            f"/v1/environments/{rows.env}",
            f"/v1/environments/{rows.env}/snapshots",
            f"/v1/environments/{rows.env}/comparisons",
            f"/v1/environments/{rows.env}/state",
            f"/v1/snapshots/{rows.snapshot}",
            f"/v1/comparisons/{rows.comparison}",
            f"/v1/jobs/{rows.snapshot_job}",
        ]

    for path in paths(own):
        r = client.get(path, headers=station)
        assert r.status_code == 200, (path, r.text)
    for path in paths(other):
        # 404, the same answer as for an id that does not exist: a station learns nothing
        # about other environments
        r = client.get(path, headers=station)
        assert r.status_code == 404 and r.json()["error"] == "NotFound", (path, r.text)
        # the unlimited read key still sees them
        assert client.get(path, headers=keys.headers("read")).status_code == 200, path
    r = client.get(f"/v1/snapshots/{other.snapshot}/pointcloud", headers=station)
    assert r.status_code == 404
    r = client.get(f"/v1/environments/{other.env}/objects/nope/history", headers=station)
    unlimited = client.get(
        f"/v1/environments/{other.env}/objects/nope/history", headers=keys.headers("read")
    )
    assert r.status_code == unlimited.status_code == 404 and r.json() == unlimited.json()

    # uploads: its own environment yes, the other one no (404 as if it did not exist)
    files = as_parts(capture())
    r = client.post(f"/v1/environments/{other.env}/snapshots", files=files, headers=station)
    assert r.status_code == 404, r.text
    r = client.post(f"/v1/environments/{own.env}/snapshots", files=files, headers=station)
    assert r.status_code == 202, r.text

    # cancel: only jobs of its own environment
    r = client.post(f"/v1/jobs/{other.snapshot_job}/cancel", headers=station)
    assert r.status_code == 404
    with session_factory() as s:
        assert jobs.get(s, other.snapshot_job).cancel_requested is False
    r = client.post(f"/v1/jobs/{own.snapshot_job}/cancel", headers=station)
    assert r.status_code == 200 and r.json()["state"] == "cancelled"


def test_cancel_needs_the_jobs_environment_or_admin(
    client: TestClient, keys: Keys, session_factory: sessionmaker[Session], sent_tasks: SentTasks
) -> None:
    with session_factory.begin() as s:
        object_job = jobs.create(s, JobKind.object, "object.prepare").id
    # an object job belongs to no environment: a capture key cannot cancel library work
    r = client.post(f"/v1/jobs/{object_job}/cancel", headers=keys.headers("capture"))
    assert r.status_code == 403 and r.json()["error"] == "Forbidden"
    r = client.post(f"/v1/jobs/{object_job}/cancel", headers=keys.headers("read"))
    assert r.status_code == 403
    r = client.post(f"/v1/jobs/{object_job}/cancel", headers=keys.headers())
    assert r.status_code == 200 and r.json()["state"] == "cancelled"


def test_key_creation_checks_environments(client: TestClient, keys: Keys) -> None:
    env = make_env(client, keys, "line-1")
    for body, needle in (
        ({"scopes": ["admin"], "environment_ids": [env]}, "admin"),
        ({"scopes": ["metrics"], "environment_ids": [env]}, "metrics"),
        ({"scopes": ["read"], "environment_ids": ["no-such-env"]}, "no-such-env"),
        ({"scopes": ["read"], "environment_ids": []}, "environment_ids"),
    ):
        r = client.post("/v1/keys", json={"name": "x", **body}, headers=keys.headers())
        assert r.status_code == 422 and needle in r.json()["detail"], (body, r.text)
    unlimited = create_key(client, keys, scopes=["read"])
    assert unlimited["environment_ids"] is None
    listed = client.get("/v1/keys", headers=keys.headers()).json()
    assert {k["id"]: k["environment_ids"] for k in listed}[unlimited["id"]] is None


def test_key_prefix_is_a_non_secret_id(client: TestClient, keys: Keys) -> None:
    created = create_key(client, keys, scopes=["read"])
    token, prefix = str(created["key"]), str(created["prefix"])
    assert prefix == "td_" + str(created["id"])[:8]
    # the token starts with the id, then the secret: nothing of the secret is stored
    assert token.startswith(prefix + "_") and len(token) > len(prefix) + 40


def test_last_admin_key_cannot_revoke_itself(
    client: TestClient, keys: Keys, session_factory: sessionmaker[Session]
) -> None:
    listed = client.get("/v1/keys", headers=keys.headers()).json()
    admin_id = next(k["id"] for k in listed if k["scopes"] == ["admin"])
    r = client.delete(f"/v1/keys/{admin_id}", headers=keys.headers())
    assert r.status_code == 409 and r.json()["error"] == "LastAdminKey", r.text
    assert client.get("/v1/keys", headers=keys.headers()).status_code == 200

    second = create_key(client, keys, scopes=["admin"])
    r = client.delete(f"/v1/keys/{admin_id}", headers=bearer(str(second["key"])))
    assert r.status_code == 200 and r.json()["revoked_at"] is not None
    assert client.get("/v1/keys", headers=keys.headers()).status_code == 401
    r = client.delete(f"/v1/keys/{second['id']}", headers=bearer(str(second["key"])))
    assert r.status_code == 409
    # other keys can still be revoked
    read_id = next(k["id"] for k in listed if k["scopes"] == ["read"])
    r = client.delete(f"/v1/keys/{read_id}", headers=bearer(str(second["key"])))
    assert r.status_code == 200
    with session_factory() as s:
        assert s.get(ApiKey, second["id"]) is not None
        assert s.get(ApiKey, second["id"]).revoked_at is None  # type: ignore[union-attr]


def test_metrics_needs_a_key(client: TestClient, keys: Keys) -> None:
    r = client.get("/metrics")
    assert r.status_code == 401
    assert client.get("/metrics", headers=keys.headers("capture")).status_code == 403
    assert "twindelta_jobs" in client.get("/metrics", headers=keys.headers("read")).text
    scraper = create_key(client, keys, scopes=["metrics"])
    r = client.get("/metrics", headers=bearer(str(scraper["key"])))
    assert r.status_code == 200 and "twindelta_http_requests_total" in r.text
    # a metrics key reads nothing else
    assert client.get("/v1/environments", headers=bearer(str(scraper["key"]))).status_code == 403


def test_metrics_refuses_a_key_limited_to_environments(client: TestClient, keys: Keys) -> None:
    env = make_env(client, keys, "line-1")
    limited = create_key(client, keys, scopes=["read"], environment_ids=[env])
    # job counts cover every environment
    assert client.get("/metrics", headers=bearer(str(limited["key"]))).status_code == 403


def test_repeated_bad_keys_get_429(
    client: TestClient, keys: Keys, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("TWINDELTA_AUTH_FAILURE_LIMIT", "3")
    monkeypatch.setenv("TWINDELTA_AUTH_FAILURE_WINDOW_S", "2.0")
    get_settings.cache_clear()
    for i in range(3):
        r = client.get("/v1/environments", headers=bearer(f"td_guess_{i}"))
        assert r.status_code == 401, r.text
    r = client.get("/v1/environments", headers=bearer("td_guess_3"))
    assert r.status_code == 429 and r.json()["error"] == "TooManyRequests"
    retry_after = int(r.headers["Retry-After"])
    assert 1 <= retry_after <= 2
    # while locked out even a good key from that address waits: a guess that happens to
    # be right must not be told apart from a wrong one
    assert client.get("/v1/environments", headers=keys.headers("read")).status_code == 429
    # a request with no key at all is not a guess: still a plain 401
    assert client.get("/v1/environments").status_code == 401
    time.sleep(retry_after + 0.05)  # the oldest failure has left the window
    assert client.get("/v1/environments", headers=keys.headers("read")).status_code == 200


def test_bad_keys_on_requests_with_a_body_count_too(
    client: TestClient, keys: Keys, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Requests with a body are authenticated before the body is read (BodyGuard): the
    same limit applies there."""
    monkeypatch.setenv("TWINDELTA_AUTH_FAILURE_LIMIT", "2")
    get_settings.cache_clear()
    body = {"name": "x", "classes": ["a"]}
    for i in range(2):
        r = client.post("/v1/environments", json=body, headers=bearer(f"td_guess_{i}"))
        assert r.status_code == 401, r.text
    r = client.post("/v1/environments", json=body, headers=keys.headers())
    assert r.status_code == 429 and int(r.headers["Retry-After"]) >= 1, r.text
    assert client.get("/v1/environments", headers=keys.headers("read")).status_code == 429


def test_good_keys_do_not_count_towards_the_limit(
    client: TestClient, keys: Keys, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("TWINDELTA_AUTH_FAILURE_LIMIT", "2")
    get_settings.cache_clear()
    for _ in range(5):
        assert client.get("/v1/environments", headers=keys.headers("read")).status_code == 200
        # a 403 (right key, wrong scope) is not a bad key either
        assert client.get("/v1/keys", headers=keys.headers("read")).status_code == 403
    assert client.get("/v1/environments", headers=bearer("td_guess")).status_code == 401
    assert client.get("/v1/environments", headers=keys.headers("read")).status_code == 200


def test_revocation_is_seen_at_once_by_a_fresh_lookup(
    client: TestClient, keys: Keys, session_factory: sessionmaker[Session]
) -> None:
    """A revocation committed by another process (here: straight in the database, not
    through this app) is refused on the next request."""
    created = create_key(client, keys, scopes=["read"])
    headers = bearer(str(created["key"]))
    assert client.get("/v1/environments", headers=headers).status_code == 200
    with session_factory.begin() as s:
        row = s.get(ApiKey, created["id"])
        assert row is not None
        row.revoked_at = auth.utcnow()
    r = client.get("/v1/environments", headers=headers)
    assert r.status_code == 401, r.text


def test_a_request_with_a_body_looks_its_key_up_once(
    client: TestClient, keys: Keys, monkeypatch: pytest.MonkeyPatch
) -> None:
    """BodyGuard checks the key before the body is read; the route's scope check uses that
    principal (403 for the wrong scope) instead of a second database lookup."""
    calls: list[object] = []
    real = auth.authenticate

    def counted(*args: object, **kwargs: object) -> auth.Principal:
        calls.append(args)
        return real(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(auth, "authenticate", counted)
    r = client.post("/v1/keys", json={"name": "other", "scopes": ["read"]}, headers=keys.headers())
    assert r.status_code == 201, r.text
    assert len(calls) == 1
    calls.clear()
    r = client.post(
        "/v1/keys", json={"name": "x", "scopes": ["read"]}, headers=keys.headers("read")
    )
    assert r.status_code == 403 and r.json()["error"] == "Forbidden", r.text
    assert len(calls) == 1
