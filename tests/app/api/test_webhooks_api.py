"""Webhook subscriptions and the delivery log over HTTP: the secret shown once, target
checks, scopes, and a dead-lettered delivery visible in the log and redelivered."""

from __future__ import annotations

import base64
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy.orm import Session, sessionmaker

from app.core import webhooks
from app.core.enums import EventType
from app.core.settings import get_settings
from tests.app.conftest import Keys, SentTasks
from tests.app.core.test_webhooks import (
    Receiver,
    drive,
    free_port,
    make_env,
    record,
)

ALL_TYPES = sorted(str(t) for t in EventType)
PUBLIC = "https://93.184.216.34/hooks/twin"


def create(client: TestClient, keys: Keys, **body: Any) -> dict[str, Any]:
    r = client.post("/v1/webhooks", json={"url": PUBLIC, **body}, headers=keys.headers())
    assert r.status_code == 201, r.text
    out: dict[str, Any] = r.json()
    return out


@pytest.fixture
def loopback_allowed(data_dir: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("TWINDELTA_WEBHOOK_RETRY_SCHEDULE_S", "[0.2, 0.2, 0.2]")
    monkeypatch.setenv("TWINDELTA_WEBHOOK_ALLOWED_NETWORKS", '["127.0.0.0/8"]')
    monkeypatch.setenv("TWINDELTA_WEBHOOK_TIMEOUT_S", "3")
    get_settings.cache_clear()


def test_create_shows_secret_once_and_reads_hide_it(client: TestClient, keys: Keys) -> None:
    made = create(client, keys)
    assert made["url"] == PUBLIC and made["active"] is True
    assert made["event_types"] == ALL_TYPES and made["environment_id"] is None
    secret = made["secret"]
    assert secret.startswith("whsec_")
    assert len(base64.b64decode(secret.removeprefix("whsec_"))) >= 24
    assert create(client, keys)["secret"] != secret
    got = client.get(f"/v1/webhooks/{made['id']}", headers=keys.headers())
    assert got.status_code == 200 and "secret" not in got.json()
    listed = client.get("/v1/webhooks", headers=keys.headers()).json()
    assert len(listed) == 2 and all("secret" not in w for w in listed)
    assert secret not in client.get("/v1/webhooks", headers=keys.headers()).text


def test_event_types_and_environment_filter(
    client: TestClient, keys: Keys, session_factory: sessionmaker[Session]
) -> None:
    env = make_env(session_factory)
    made = create(client, keys, event_types=["job.failed"], environment_id=env)
    assert made["event_types"] == ["job.failed"] and made["environment_id"] == env
    r = client.post(
        "/v1/webhooks", json={"url": PUBLIC, "event_types": ["nope"]}, headers=keys.headers()
    )
    assert r.status_code == 422 and r.json()["error"] == "InvalidInput"
    r = client.post(
        "/v1/webhooks", json={"url": PUBLIC, "environment_id": "nope"}, headers=keys.headers()
    )
    assert r.status_code == 422 and "environment" in r.json()["detail"]


@pytest.mark.parametrize(
    "url",
    [
        "ftp://93.184.216.34/x",
        "not a url",
        "http://127.0.0.1:8080/hook",
        "http://localhost/hook",
        "http://10.0.0.5/hook",
        "http://192.168.0.2/hook",
        "http://169.254.169.254/",
        "http://[fd12:3456::1]/hook",
    ],
)
def test_non_http_and_private_targets_refused(client: TestClient, keys: Keys, url: str) -> None:
    r = client.post("/v1/webhooks", json={"url": url}, headers=keys.headers())
    assert r.status_code == 422, r.text
    assert r.json()["error"] in {"InvalidInput", "WebhookTargetRefused"}
    assert client.get("/v1/webhooks", headers=keys.headers()).json() == []


def test_allow_list_admits_loopback_only(
    client: TestClient, keys: Keys, loopback_allowed: None
) -> None:
    create(client, keys, url="http://127.0.0.1:8080/hook")
    r = client.post("/v1/webhooks", json={"url": "http://10.0.0.5/h"}, headers=keys.headers())
    assert r.status_code == 422 and r.json()["error"] == "WebhookTargetRefused"


def test_scopes_unknown_ids_and_deactivate(client: TestClient, keys: Keys) -> None:
    made = create(client, keys)
    for which in ("read", "capture"):
        r = client.post("/v1/webhooks", json={"url": PUBLIC}, headers=keys.headers(which))
        assert r.status_code == 403
        assert client.get("/v1/webhooks", headers=keys.headers(which)).status_code == 403
    assert client.get("/v1/webhooks").status_code == 401
    for method, path in (
        ("GET", "/v1/webhooks/nope"),
        ("DELETE", "/v1/webhooks/nope"),
        ("GET", "/v1/webhooks/nope/deliveries"),
        ("POST", f"/v1/webhooks/{made['id']}/deliveries/nope/redeliver"),
    ):
        r = client.request(method, path, headers=keys.headers())
        assert r.status_code == 404 and r.json()["error"] == "NotFound", path
    r = client.delete(f"/v1/webhooks/{made['id']}", headers=keys.headers())
    assert r.status_code == 200 and r.json()["active"] is False
    assert r.json()["deactivated_at"] is not None
    got = client.get(f"/v1/webhooks/{made['id']}", headers=keys.headers()).json()
    assert got["active"] is False


def test_dead_letter_in_the_log_then_redelivery(
    client: TestClient,
    keys: Keys,
    session_factory: sessionmaker[Session],
    sent_tasks: SentTasks,
    loopback_allowed: None,
) -> None:
    env = make_env(session_factory)
    port = free_port()  # the receiver is down for the whole schedule
    made = create(client, keys, url=f"http://127.0.0.1:{port}/hook")
    event_id = record(session_factory, env)
    drive(session_factory, sent_tasks)

    log = client.get(f"/v1/webhooks/{made['id']}/deliveries", headers=keys.headers())
    assert log.status_code == 200
    [delivery] = log.json()
    assert delivery["state"] == "failed" and delivery["event"] == event_id
    assert delivery["event_type"] == "comparison.completed"
    assert delivery["next_attempt_at"] is None and delivery["finished_at"] is not None
    assert [a["number"] for a in delivery["attempts"]] == [1, 2, 3, 4]
    assert all("ConnectError" in a["error"] for a in delivery["attempts"])
    assert all(a["status_code"] is None for a in delivery["attempts"])
    failed = client.get(
        f"/v1/webhooks/{made['id']}/deliveries?state=failed", headers=keys.headers()
    )
    assert len(failed.json()) == 1
    ok = client.get(f"/v1/webhooks/{made['id']}/deliveries?state=succeeded", headers=keys.headers())
    assert ok.json() == []

    receiver = Receiver(port=port).start()
    try:
        r = client.post(
            f"/v1/webhooks/{made['id']}/deliveries/{delivery['id']}/redeliver",
            headers=keys.headers(),
        )
        assert r.status_code == 202 and r.json()["state"] == "pending"
        assert sent_tasks.calls[-1] == ("webhooks.deliver", {"delivery_id": delivery["id"]})
        drive(session_factory, sent_tasks)
        [hit] = receiver.on("/hook")
        assert hit.headers["webhook-id"] == event_id  # the same id as every earlier attempt
    finally:
        receiver.stop()
    [delivery] = client.get(f"/v1/webhooks/{made['id']}/deliveries", headers=keys.headers()).json()
    assert delivery["state"] == "succeeded" and delivery["last_status_code"] == 200
    last = delivery["attempts"][-1]
    assert last["number"] == 5 and last["status_code"] == 200 and last["latency_ms"] > 0
    assert '"status": 200' in last["response_excerpt"]

    # a deactivated subscription cannot redeliver
    client.delete(f"/v1/webhooks/{made['id']}", headers=keys.headers())
    r = client.post(
        f"/v1/webhooks/{made['id']}/deliveries/{delivery['id']}/redeliver",
        headers=keys.headers(),
    )
    assert r.status_code == 409 and r.json()["error"] == "WebhookInactive"


def test_rotate_secret_shows_the_new_one_once_and_keeps_the_old_for_the_overlap(
    client: TestClient,
    keys: Keys,
    loopback_allowed: None,
    session_factory: sessionmaker[Session],
    sent_tasks: SentTasks,
) -> None:
    receiver = Receiver().start()
    try:
        made = create(client, keys, url=receiver.url())
        path = f"/v1/webhooks/{made['id']}/rotate-secret"
        r = client.post(path, headers=keys.headers())
        assert r.status_code == 200, r.text
        rotated = r.json()
        assert rotated["id"] == made["id"] and rotated["secret"].startswith("whsec_")
        assert rotated["secret"] != made["secret"]
        assert rotated["previous_secret_expires_at"] is not None
        got = client.get(f"/v1/webhooks/{made['id']}", headers=keys.headers()).json()
        assert "secret" not in got and got["previous_secret_expires_at"] is not None
        record(session_factory, make_env(session_factory))
        assert drive(session_factory, sent_tasks) == ["succeeded"]
        [hit] = receiver.on("/hook")
        assert len(hit.headers["webhook-signature"].split(" ")) == 2
        for secret in (made["secret"], rotated["secret"]):
            webhooks.verify_signature(secret, hit.headers, hit.body)
    finally:
        receiver.stop()
    assert client.post(path, headers=keys.headers("read")).status_code == 403
    r = client.post("/v1/webhooks/nope/rotate-secret", headers=keys.headers())
    assert r.status_code == 404 and r.json()["error"] == "NotFound"
    client.delete(f"/v1/webhooks/{made['id']}", headers=keys.headers())
    r = client.post(path, headers=keys.headers())
    assert r.status_code == 409 and r.json()["error"] == "WebhookInactive"
