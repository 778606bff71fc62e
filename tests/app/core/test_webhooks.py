"""Webhooks without Celery: signatures, fan-out, the claim/send/record cycle against a real
HTTP receiver on loopback, retries on the database schedule, ordering per environment,
leases, target checks.

``drive()`` plays worker and beat in this process: it runs every ``webhooks.deliver`` the
code sent after commit (the deliver task's three steps) and the dispatcher, until the
deliveries are final."""

from __future__ import annotations

import base64
import ipaddress
import itertools
import json
import select as io_select
import socket
import ssl
import stat
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import pytest
from alembic import command
from alembic.config import Config
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID
from pydantic import SecretStr, ValidationError
from sqlalchemy import select, text, update
from sqlalchemy.orm import Session, sessionmaker

from app.client import free_port
from app.core import db, events, secretbox, webhooks
from app.core.enums import DeliveryState, EventType
from app.core.errors import Conflict, InvalidInput
from app.core.models import Delivery, DeliveryAttempt, Environment, WebhookSubscription, utcnow
from app.core.settings import Settings, get_settings
from tests.app.conftest import SentTasks
from tests.conftest import REPO_ROOT

# --- a real receiver on loopback --------------------------------------------------------------


@dataclass
class Hit:
    path: str
    headers: dict[str, str]
    body: bytes
    at: float
    status: int
    done_at: float = 0.0

    @property
    def event(self) -> dict[str, Any]:
        out: dict[str, Any] = json.loads(self.body)
        return out


@dataclass
class Receiver:
    """An HTTP server in a thread. ``plan(path, [500, 500])`` makes the next answers on
    ``path`` 500, 500, then 200; ``delays`` sleep before answering; ``gate(path)`` holds
    every answer on ``path`` until the returned event is set."""

    port: int = 0
    host: str = "127.0.0.1"
    tls: ssl.SSLContext | None = None  # serve https with this context
    hits: list[Hit] = field(default_factory=list)
    plans: dict[str, list[int]] = field(default_factory=dict)
    delays: dict[str, list[float]] = field(default_factory=dict)
    gates: dict[str, threading.Event] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)
    server: ThreadingHTTPServer | None = None

    def start(self) -> Receiver:
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:
                body = self.rfile.read(int(self.headers.get("content-length", "0")))
                with receiver.lock:
                    plan = receiver.plans.get(self.path, [])
                    status = plan.pop(0) if plan else 200
                    delays = receiver.delays.get(self.path, [])
                    delay = delays.pop(0) if delays else 0.0
                    hit = Hit(
                        self.path,
                        {k.lower(): v for k, v in self.headers.items()},
                        body,
                        time.monotonic(),
                        status,
                    )
                    receiver.hits.append(hit)
                time.sleep(delay)
                gate = receiver.gates.get(self.path)
                if gate is not None:
                    gate.wait(30)
                answer = json.dumps({"status": status, "pad": "x" * 3000}).encode()
                self.send_response(status)
                self.send_header("content-length", str(len(answer)))
                self.end_headers()
                self.wfile.write(answer)
                hit.done_at = time.monotonic()

            def log_message(self, *args: object) -> None:
                pass

        ThreadingHTTPServer.allow_reuse_address = True
        self.server = ThreadingHTTPServer((self.host, self.port), Handler)
        if self.tls is not None:
            self.server.socket = self.tls.wrap_socket(self.server.socket, server_side=True)
        self.server.daemon_threads = True
        self.port = self.server.server_address[1]
        threading.Thread(target=self.server.serve_forever, daemon=True).start()
        return self

    def stop(self) -> None:
        if self.server is not None:
            for gate in self.gates.values():
                gate.set()
            self.server.shutdown()
            self.server.server_close()
            self.server = None

    def url(self, path: str = "/hook") -> str:
        scheme = "https" if self.tls is not None else "http"
        return f"{scheme}://{self.host}:{self.port}{path}"

    def plan(self, path: str, statuses: list[int], delays: list[float] | None = None) -> None:
        with self.lock:
            self.plans[path] = list(statuses)
            self.delays[path] = list(delays or [])

    def gate(self, path: str) -> threading.Event:
        gate = self.gates[path] = threading.Event()
        return gate

    def on(self, path: str) -> list[Hit]:
        with self.lock:
            return [h for h in self.hits if h.path == path]


@pytest.fixture
def receiver() -> Iterator[Receiver]:
    r = Receiver().start()
    yield r
    r.stop()


@dataclass
class DripConnection:
    webhook_id: str | None
    opened_at: float
    path: str = ""
    closed_at: float | None = None  # when the client hung up (or the drip ended)


@dataclass
class DripServer:
    """A receiver that reads the request, then answers a valid 200 one byte every
    ``interval_s`` for at most ``for_s`` seconds: every single read the client makes gets a
    byte well within any per-read timeout. Notes when each connection opened and when the
    client hung up (seen at once: the server waits for the next byte with select)."""

    interval_s: float = 1.5
    for_s: float = 30.0
    connections: list[DripConnection] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)
    stopped: threading.Event = field(default_factory=threading.Event)
    listener: socket.socket | None = None
    port: int = 0

    def start(self) -> DripServer:
        self.listener = socket.create_server(("127.0.0.1", 0), backlog=32)
        self.port = self.listener.getsockname()[1]
        threading.Thread(target=self._accept, daemon=True).start()
        return self

    def url(self, path: str = "/drip") -> str:
        return f"http://127.0.0.1:{self.port}{path}"

    def _accept(self) -> None:
        assert self.listener is not None
        while not self.stopped.is_set():
            try:
                conn, _ = self.listener.accept()
            except OSError:
                return
            threading.Thread(target=self._drip, args=(conn,), daemon=True).start()

    def _drip(self, conn: socket.socket) -> None:
        record = DripConnection(None, time.monotonic())
        with self.lock:
            self.connections.append(record)
        try:
            request = b""
            while b"\r\n\r\n" not in request:
                chunk = conn.recv(65536)
                if not chunk:
                    return
                request += chunk
            raw_head, body = request.split(b"\r\n\r\n", 1)
            record.path = raw_head.split(b" ", 2)[1].decode("latin-1")
            length = 0
            for line in raw_head.decode("latin-1").lower().split("\r\n"):
                name, _, value = line.partition(":")
                if name == "webhook-id":
                    record.webhook_id = value.strip()
                elif name == "content-length":
                    length = int(value)
            while len(body) < length:
                chunk = conn.recv(65536)
                if not chunk:
                    return
                body += chunk
            answer = b"HTTP/1.1 200 OK\r\ncontent-length: 2\r\nconnection: close\r\n\r\nok"
            end = record.opened_at + self.for_s
            for byte in answer:
                readable, _, _ = io_select.select([conn], [], [], self.interval_s)
                if readable and not conn.recv(65536):
                    return  # the client hung up
                if self.stopped.is_set() or time.monotonic() > end:
                    return
                conn.sendall(bytes([byte]))
        except OSError:
            return
        finally:
            record.closed_at = time.monotonic()
            conn.close()

    def open_now(self) -> list[DripConnection]:
        with self.lock:
            return [c for c in self.connections if c.closed_at is None]

    def stop(self) -> None:
        self.stopped.set()
        if self.listener is not None:
            self.listener.close()


def overlapping(connections: list[DripConnection]) -> list[tuple[float, float]]:
    """Pairs of connections carrying the same event to the same path at the same time."""
    out = []
    for a, b in itertools.combinations(connections, 2):
        if a.webhook_id is None or (a.path, a.webhook_id) != (b.path, b.webhook_id):
            continue
        a_end, b_end = a.closed_at or time.monotonic(), b.closed_at or time.monotonic()
        if a.opened_at < b_end and b.opened_at < a_end:
            out.append((a.opened_at, b.opened_at))
    return out


@pytest.fixture
def webhook_settings(data_dir: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    """A short retry schedule, loopback allowed, a short timeout."""
    monkeypatch.setenv("TWINDELTA_WEBHOOK_RETRY_SCHEDULE_S", "[0.2, 0.2, 0.2]")
    monkeypatch.setenv("TWINDELTA_WEBHOOK_ALLOWED_NETWORKS", '["127.0.0.0/8"]')
    monkeypatch.setenv("TWINDELTA_WEBHOOK_TIMEOUT_S", "3")
    get_settings.cache_clear()


# --- helpers -------------------------------------------------------------------------------


def make_env(factory: sessionmaker[Session], name: str = "line-1") -> str:
    with factory.begin() as s:
        env = Environment(name=name, classes=["power_drill"])
        s.add(env)
        s.flush()
        return env.id


def subscribe(
    factory: sessionmaker[Session],
    url: str,
    *,
    types: list[EventType] | None = None,
    environment_id: str | None = None,
) -> tuple[str, str]:
    with factory.begin() as s:
        sub = webhooks.create_subscription(
            s, get_settings(), url=url, event_types=types, environment_id=environment_id
        )
        return sub.id, webhooks.current_secret(get_settings(), sub)


def record(
    factory: sessionmaker[Session],
    env_id: str | None,
    n: int = 0,
    event_type: EventType = EventType.comparison_completed,
) -> str:
    with factory.begin() as s:
        return events.record(
            s, event_type, environment_id=env_id, subject=f"comparisons/c{n}", data={"n": n}
        ).id


def deliver_once(delivery_id: str) -> str:
    """The ``webhooks.deliver`` task: claim (short transaction) → send → record."""
    settings = get_settings()
    with db.transaction() as s:
        claim = webhooks.claim(s, delivery_id, settings)
    if claim is None:
        return "skipped"
    outcome = webhooks.send(claim, settings)
    with db.transaction() as s:
        return webhooks.record_attempt(s, claim, outcome, settings)


def deliveries(factory: sessionmaker[Session], **where: Any) -> list[Delivery]:
    with factory() as s:
        query = select(Delivery).filter_by(**where).order_by(Delivery.seq, Delivery.id)
        return list(s.scalars(query))


def attempts_of(factory: sessionmaker[Session], delivery_id: str) -> list[DeliveryAttempt]:
    with factory() as s:
        query = select(DeliveryAttempt).where(DeliveryAttempt.delivery_id == delivery_id)
        return list(s.scalars(query.order_by(DeliveryAttempt.number)))


def drive(factory: sessionmaker[Session], sent: SentTasks, timeout_s: float = 10.0) -> list[str]:
    """Worker and beat in one loop until no delivery is pending; returns the task results."""
    results: list[str] = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        while sent.calls:
            name, kwargs = sent.calls.pop(0)
            if name == "webhooks.deliver":
                results.append(deliver_once(kwargs["delivery_id"]))
        if not deliveries(factory, state=DeliveryState.pending):
            return results
        with db.transaction() as s:
            webhooks.dispatch_due(s)
        time.sleep(0.02)
    raise AssertionError(f"deliveries still pending after {timeout_s} s: {results}")


# --- signatures ----------------------------------------------------------------------------


@pytest.mark.parametrize("stamp", ["9" * 400, "-" + "9" * 400, "1e9", " ", "١٢٣"])
def test_a_hostile_timestamp_is_a_verification_error(stamp: str) -> None:
    secret = webhooks.new_secret()
    body = b"{}"
    headers = {**webhooks.signed_headers(secret, "e1", body, int(time.time()))}
    headers["webhook-timestamp"] = stamp
    with pytest.raises(webhooks.WebhookVerificationError, match="webhook-timestamp"):
        webhooks.verify_signature(secret, headers, body)


def test_secret_and_signature_verify_and_fail() -> None:
    secret = webhooks.new_secret()
    assert secret.startswith("whsec_")
    assert len(base64.b64decode(secret.removeprefix("whsec_"))) >= 24
    body = b'{"specversion":"1.0","id":"e1"}'
    now = int(time.time())
    headers = webhooks.signed_headers(secret, "e1", body, now)
    assert headers["webhook-signature"].startswith("v1,")
    webhooks.verify_signature(secret, headers, body)
    upper = {k.upper(): v for k, v in headers.items()}
    webhooks.verify_signature(secret, upper, body)  # header names are case-insensitive
    rotated = {**headers, "webhook-signature": "v1,bm9wZQ== " + headers["webhook-signature"]}
    webhooks.verify_signature(secret, rotated, body)  # any one of several signatures
    bad = [
        (webhooks.new_secret(), headers, body, "wrong secret"),
        (secret, headers, body + b" ", "tampered body"),
        (secret, {**headers, "webhook-id": "e2"}, body, "other id"),
        (secret, {k: v for k, v in headers.items() if k != "webhook-id"}, body, "missing id"),
        (
            secret,
            {**headers, "webhook-signature": "v2," + headers["webhook-signature"][3:]},
            body,
            "unknown version",
        ),
    ]
    for key, hdrs, payload, why in bad:
        with pytest.raises(webhooks.WebhookVerificationError):
            webhooks.verify_signature(key, hdrs, payload)
            pytest.fail(why)
    old = webhooks.signed_headers(secret, "e1", body, now - 301)
    with pytest.raises(webhooks.WebhookVerificationError, match="tolerance"):
        webhooks.verify_signature(secret, old, body)
    webhooks.verify_signature(secret, old, body, tolerance_s=600)
    future = webhooks.signed_headers(secret, "e1", body, now + 301)
    with pytest.raises(webhooks.WebhookVerificationError, match="tolerance"):
        webhooks.verify_signature(secret, future, body)


# --- target addresses ----------------------------------------------------------------------


@pytest.mark.parametrize(
    "url",
    [
        "ftp://93.184.216.34/x",
        "file:///etc/passwd",
        "javascript:alert(1)",
        "http:///nohost",
        "http://127.0.0.1:8000/hook",
        "http://localhost/hook",
        "http://10.1.2.3/hook",
        "http://172.16.0.1/hook",
        "http://192.168.1.10/hook",
        "http://169.254.169.254/latest/meta-data",
        "http://[::1]/hook",
        "http://[fd00::1]/hook",
        "http://[fe80::1]/hook",
        "http://[::ffff:10.0.0.1]/hook",
        "http://0.0.0.0/hook",
    ],
)
def test_target_refused(url: str) -> None:
    with pytest.raises(InvalidInput):
        webhooks.check_target(url, [])


def test_target_allow_list() -> None:
    webhooks.check_target("https://93.184.216.34/hook", [])
    webhooks.check_target("http://[2606:4700::1111]/hook", [])
    loopback = webhooks.allowed_networks(
        get_settings().model_copy(update={"webhook_allowed_networks": ["127.0.0.0/8"]})
    )
    webhooks.check_target("http://127.0.0.1:9/hook", loopback)
    webhooks.check_target("http://localhost:9/hook", [*loopback, ipaddress.ip_network("::1")])
    with pytest.raises(InvalidInput, match="non-public"):
        webhooks.check_target("http://10.0.0.1/hook", loopback)


# --- fan-out -------------------------------------------------------------------------------


def test_fan_out_matches_type_environment_and_activity(
    session_factory: sessionmaker[Session], sent_tasks: SentTasks, webhook_settings: None
) -> None:
    env_a, env_b = make_env(session_factory, "a"), make_env(session_factory, "b")
    url = "http://127.0.0.1:9/hook"
    every, _ = subscribe(session_factory, url)
    only_a, _ = subscribe(session_factory, url, environment_id=env_a)
    failed_only, _ = subscribe(session_factory, url, types=[EventType.job_failed])
    gone, _ = subscribe(session_factory, url)
    with session_factory.begin() as s:
        webhooks.deactivate(s, gone)
    sent_tasks.calls.clear()

    event_a = record(session_factory, env_a)
    event_b = record(session_factory, env_b)
    event_fail = record(session_factory, None, event_type=EventType.job_failed)

    def subs_of(event_id: str) -> set[str]:
        return {d.subscription_id for d in deliveries(session_factory, event_id=event_id)}

    assert subs_of(event_a) == {every, only_a}
    assert subs_of(event_b) == {every}
    assert subs_of(event_fail) == {every, failed_only}
    assert sent_tasks.names() == ["webhooks.deliver"] * 5
    keys = {d.ordering_key for d in deliveries(session_factory, subscription_id=every)}
    assert keys == {f"{every}:{env_a}", f"{every}:{env_b}", f"{every}:-"}


def test_nothing_sent_when_the_transaction_rolls_back(
    session_factory: sessionmaker[Session], sent_tasks: SentTasks, webhook_settings: None
) -> None:
    env = make_env(session_factory)
    subscribe(session_factory, "http://127.0.0.1:9/hook")
    sent_tasks.calls.clear()
    with pytest.raises(RuntimeError), session_factory.begin() as s:
        events.record(s, EventType.job_failed, environment_id=env, subject=None, data={})
        raise RuntimeError("the state change failed")
    assert sent_tasks.calls == [] and deliveries(session_factory) == []


# --- delivery against a real receiver --------------------------------------------------------


def test_delivered_as_signed_cloudevent_with_data_verbatim(
    session_factory: sessionmaker[Session],
    sent_tasks: SentTasks,
    webhook_settings: None,
    receiver: Receiver,
) -> None:
    env = make_env(session_factory)
    sub_id, secret = subscribe(session_factory, receiver.url())
    change = {
        "type": "moved",
        "object": "power_drill",
        "instance_id": "i-1",
        "pose": [[1.0, 0, 0, 0.5], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
        "previous_pose": [[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
        "pose_quality": {"fitness": 0.93, "inlier_rmse": 0.0021, "verified": True},
    }
    data = {"comparison": "c1", "changes": [change], "note": "ünïcode"}
    with session_factory.begin() as s:
        event = events.record(
            s,
            EventType.comparison_completed,
            environment_id=env,
            subject="comparisons/c1",
            data=data,
        )
        event_id = event.id
    assert drive(session_factory, sent_tasks) == ["succeeded"]

    [hit] = receiver.on("/hook")
    webhooks.verify_signature(secret, hit.headers, hit.body)
    with pytest.raises(webhooks.WebhookVerificationError):
        webhooks.verify_signature(webhooks.new_secret(), hit.headers, hit.body)
    assert hit.headers["webhook-id"] == event_id
    assert abs(int(hit.headers["webhook-timestamp"]) - time.time()) < 5
    assert hit.headers["content-type"].startswith("application/cloudevents+json")
    ce = hit.event
    assert ce["specversion"] == "1.0" and ce["id"] == event_id
    assert ce["type"] == "comparison.completed" and ce["subject"] == "comparisons/c1"
    assert ce["source"] == f"/twindelta/environments/{env}"
    assert ce["datacontenttype"] == "application/json"
    assert ce["time"].endswith("Z") and "T" in ce["time"]
    assert ce["data"] == data
    [delivery] = deliveries(session_factory, subscription_id=sub_id)
    assert delivery.state == DeliveryState.succeeded and delivery.last_status_code == 200
    [attempt] = attempts_of(session_factory, delivery.id)
    assert attempt.status_code == 200 and attempt.error is None
    assert attempt.latency_ms is not None and 0 < attempt.latency_ms < 3000
    assert attempt.response_excerpt is not None
    assert len(attempt.response_excerpt.encode()) <= 1024  # the answer is ~3 KB


def test_500_twice_then_200_arrives_three_times_with_one_id(
    session_factory: sessionmaker[Session],
    sent_tasks: SentTasks,
    webhook_settings: None,
    receiver: Receiver,
) -> None:
    env = make_env(session_factory)
    _, secret = subscribe(session_factory, receiver.url())
    receiver.plan("/hook", [500, 500])
    event_id = record(session_factory, env)
    drive(session_factory, sent_tasks)

    hits = receiver.on("/hook")
    assert [h.status for h in hits] == [500, 500, 200]
    assert {h.headers["webhook-id"] for h in hits} == {event_id}
    for h in hits:
        webhooks.verify_signature(secret, h.headers, h.body)
    gaps = [b.at - a.at for a, b in itertools.pairwise(hits)]
    assert all(g >= 0.2 * 0.8 - 0.01 for g in gaps), gaps  # the schedule, with jitter
    [delivery] = deliveries(session_factory)
    assert delivery.state == DeliveryState.succeeded and delivery.attempts == 3
    log = attempts_of(session_factory, delivery.id)
    assert [(a.number, a.status_code) for a in log] == [(1, 500), (2, 500), (3, 200)]
    assert log[0].error == "HTTP 500" and log[2].error is None


def test_down_receiver_dead_letters_then_redelivery_succeeds(
    session_factory: sessionmaker[Session],
    sent_tasks: SentTasks,
    webhook_settings: None,
) -> None:
    env = make_env(session_factory)
    port = free_port()  # nothing listens here
    sub_id, _ = subscribe(session_factory, f"http://127.0.0.1:{port}/hook")
    record(session_factory, env)
    drive(session_factory, sent_tasks)
    [delivery] = deliveries(session_factory)
    assert delivery.state == DeliveryState.failed and delivery.finished_at is not None
    log = attempts_of(session_factory, delivery.id)
    assert len(log) == 1 + len(get_settings().webhook_retry_schedule_s)
    assert all(a.status_code is None and "ConnectError" in (a.error or "") for a in log)

    late = Receiver(port=port).start()  # the receiver comes back
    try:
        with session_factory.begin() as s:
            webhooks.redeliver(s, sub_id, delivery.id)
        assert drive(session_factory, sent_tasks) == ["succeeded"]
        assert len(late.on("/hook")) == 1
    finally:
        late.stop()
    [delivery] = deliveries(session_factory)
    assert delivery.state == DeliveryState.succeeded and delivery.attempts == 5
    assert [a.status_code for a in attempts_of(session_factory, delivery.id)][-1] == 200


def test_order_per_environment_and_other_environments_not_blocked(
    session_factory: sessionmaker[Session],
    sent_tasks: SentTasks,
    webhook_settings: None,
    receiver: Receiver,
) -> None:
    env_a, env_b = make_env(session_factory, "a"), make_env(session_factory, "b")
    subscribe(session_factory, receiver.url())
    receiver.plan("/hook", [500])  # the first event of environment a needs a retry
    a1, a2, a3 = (record(session_factory, env_a, n) for n in (1, 2, 3))
    b1 = record(session_factory, env_b, 4)
    drive(session_factory, sent_tasks)

    got = [(h.headers["webhook-id"], h.status) for h in receiver.on("/hook")]
    of_a = [g for g in got if g[0] in {a1, a2, a3}]
    assert of_a == [(a1, 500), (a1, 200), (a2, 200), (a3, 200)]
    # environment b's event did not wait behind a's retry
    assert got.index((b1, 200)) < got.index((a1, 200))


def test_dispatcher_sends_only_due_heads(
    session_factory: sessionmaker[Session],
    sent_tasks: SentTasks,
    webhook_settings: None,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("TWINDELTA_WEBHOOK_RETRY_SCHEDULE_S", "[10]")  # due in 8 to 12 s
    get_settings.cache_clear()
    env = make_env(session_factory)
    subscribe(session_factory, f"http://127.0.0.1:{free_port()}/hook")
    first, second = record(session_factory, env, 1), record(session_factory, env, 2)
    d1, d2 = (deliveries(session_factory, event_id=e)[0].id for e in (first, second))
    sent_tasks.calls.clear()
    assert deliver_once(d2) == "retrying"  # asked for the second: the head (first) is sent
    assert [a.number for a in attempts_of(session_factory, d1)] == [1]
    assert attempts_of(session_factory, d2) == []
    assert deliver_once(d2) == "skipped"  # the head is waiting for its retry; d2 waits too
    now = utcnow()
    with db.transaction() as s:
        assert webhooks.dispatch_due(s, now) == []  # not due yet; d2 is not a head
    with db.transaction() as s:
        assert webhooks.dispatch_due(s, now + timedelta(seconds=13)) == [d1]
    with db.transaction() as s:  # already sent: not again until it seems lost
        assert webhooks.dispatch_due(s, now + timedelta(seconds=14)) == []
        assert webhooks.dispatch_due(s, now + timedelta(seconds=13 + 61)) == [d1]
    assert sent_tasks.calls == [("webhooks.deliver", {"delivery_id": d1})] * 2


def test_claim_is_exclusive_lease_expires_and_stale_attempt_is_fenced(
    session_factory: sessionmaker[Session],
    sent_tasks: SentTasks,
    webhook_settings: None,
    receiver: Receiver,
) -> None:
    env = make_env(session_factory)
    subscribe(session_factory, receiver.url())
    record(session_factory, env)
    [d] = deliveries(session_factory)
    settings = get_settings()
    now = utcnow()
    with db.transaction() as s:
        first = webhooks.claim(s, d.id, settings, now)
    with db.transaction() as s:
        assert webhooks.claim(s, d.id, settings, now) is None  # in flight: nobody else
        assert webhooks.dispatch_due(s, now + timedelta(seconds=1)) == []
    assert first is not None and first.attempt == 1
    # the worker holding attempt 1 dies; once its lease is over another worker takes it
    later = now + timedelta(seconds=webhooks.lease_s(settings) + 1)
    with db.transaction() as s:
        assert webhooks.dispatch_due(s, later) == [d.id]
        second = webhooks.claim(s, d.id, settings, later)
    assert second is not None and second.attempt == 2
    outcome = webhooks.send(second, settings)
    with db.transaction() as s:
        assert webhooks.record_attempt(s, second, outcome, settings) == "succeeded"
    # the zombie attempt 1 finishes late: logged, but it cannot change the delivery
    with db.transaction() as s:
        bad = webhooks.Outcome(False, 500, 1.0, "late", "HTTP 500")
        assert webhooks.record_attempt(s, first, bad, settings) == "lost"
    [d] = deliveries(session_factory)
    assert d.state == DeliveryState.succeeded and d.attempts == 2
    assert len(receiver.on("/hook")) == 1


def test_slow_receiver_does_not_block_another_subscription(
    session_factory: sessionmaker[Session],
    sent_tasks: SentTasks,
    webhook_settings: None,
    receiver: Receiver,
) -> None:
    env = make_env(session_factory)
    slow_sub, _ = subscribe(session_factory, receiver.url("/slow"))
    fast_sub, _ = subscribe(session_factory, receiver.url("/fast"))
    gate = receiver.gate("/slow")  # the slow receiver hangs until the gate opens
    record(session_factory, env)
    [slow] = deliveries(session_factory, subscription_id=slow_sub)
    [fast] = deliveries(session_factory, subscription_id=fast_sub)
    settings = get_settings()
    with db.transaction() as s:
        claim = webhooks.claim(s, slow.id, settings)
    assert claim is not None
    result: list[webhooks.Outcome] = []
    worker = threading.Thread(target=lambda: result.append(webhooks.send(claim, settings)))
    worker.start()  # one worker is stuck on the slow receiver, holding no session
    deadline = time.monotonic() + 5
    while not receiver.on("/slow") and time.monotonic() < deadline:
        time.sleep(0.01)
    assert deliver_once(fast.id) == "succeeded"  # another worker is not held up
    assert worker.is_alive() and len(receiver.on("/fast")) == 1
    gate.set()
    worker.join()
    with db.transaction() as s:
        assert webhooks.record_attempt(s, claim, result[0], settings) == "succeeded"


def test_private_target_refused_again_at_delivery_time(
    session_factory: sessionmaker[Session],
    sent_tasks: SentTasks,
    webhook_settings: None,
    receiver: Receiver,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    env = make_env(session_factory)
    subscribe(session_factory, receiver.url())
    monkeypatch.setenv("TWINDELTA_WEBHOOK_ALLOWED_NETWORKS", "[]")  # the operator revokes it
    get_settings.cache_clear()
    record(session_factory, env)
    drive(session_factory, sent_tasks)
    [d] = deliveries(session_factory)
    assert d.state == DeliveryState.failed and receiver.on("/hook") == []
    assert all("refused" in (a.error or "") for a in attempts_of(session_factory, d.id))


def test_deactivate_ends_pending_deliveries(
    session_factory: sessionmaker[Session], sent_tasks: SentTasks, webhook_settings: None
) -> None:
    env = make_env(session_factory)
    sub_id, _ = subscribe(session_factory, f"http://127.0.0.1:{free_port()}/hook")
    record(session_factory, env)
    with session_factory.begin() as s:
        webhooks.deactivate(s, sub_id)
    [d] = deliveries(session_factory)
    assert d.state == DeliveryState.failed and d.last_error == "subscription deactivated"
    assert drive(session_factory, sent_tasks) == ["skipped"]
    record(session_factory, env, 2)
    assert len(deliveries(session_factory)) == 1  # nothing new for an inactive subscription


# --- hostile receivers and networks ----------------------------------------------------------


def test_drip_receiver_attempt_ends_at_its_overall_deadline(
    session_factory: sessionmaker[Session],
    sent_tasks: SentTasks,
    webhook_settings: None,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """One byte every 1.5 s never trips a per-read timeout; the attempt still ends at
    ``webhook_timeout_s`` (2 s here), is logged as a timeout and is retried later."""
    monkeypatch.setenv("TWINDELTA_WEBHOOK_TIMEOUT_S", "2")
    get_settings.cache_clear()
    drip = DripServer(interval_s=1.5, for_s=12.0).start()
    try:
        env = make_env(session_factory)
        subscribe(session_factory, drip.url())
        record(session_factory, env)
        [d] = deliveries(session_factory)
        start = time.monotonic()
        assert deliver_once(d.id) == "retrying"
        elapsed = time.monotonic() - start
        assert elapsed < 2.0 + 0.8, f"the attempt took {elapsed:.1f} s"
        [attempt] = attempts_of(session_factory, d.id)
        assert attempt.status_code is None and "deadline" in (attempt.error or ""), attempt.error
        [conn] = drip.connections
        deadline = time.monotonic() + 2
        while conn.closed_at is None and time.monotonic() < deadline:
            time.sleep(0.02)
        assert conn.closed_at is not None and conn.closed_at - conn.opened_at < 2.8
        [d] = deliveries(session_factory)
        assert d.state == DeliveryState.pending and d.locked_until is None
    finally:
        drip.stop()


def test_an_attempt_never_runs_into_its_lease_margin(
    session_factory: sessionmaker[Session],
    sent_tasks: SentTasks,
    webhook_settings: None,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The lease is the attempt's deadline plus a margin, and an attempt stops before the
    margin however late it started sending: no other worker can claim the delivery (and
    send the event again) while this attempt still talks to the receiver."""
    monkeypatch.setenv("TWINDELTA_WEBHOOK_TIMEOUT_S", "8")
    get_settings.cache_clear()
    settings = get_settings()
    assert webhooks.lease_s(settings) == 8 + webhooks.LEASE_MARGIN_S
    drip = DripServer(interval_s=1.5, for_s=12.0).start()
    try:
        subscribe(session_factory, drip.url())
        record(session_factory, make_env(session_factory))
        [d] = deliveries(session_factory)
        # claimed 7 s ago (its worker was slow to start sending): 1 s left before the margin
        seven_ago = utcnow() - timedelta(seconds=7)
        with db.transaction() as s:
            s.execute(update(Delivery).where(Delivery.id == d.id).values(next_attempt_at=seven_ago))
            claim = webhooks.claim(s, d.id, settings, seven_ago)
        assert claim is not None
        start = time.monotonic()
        outcome = webhooks.send(claim, settings)
        elapsed = time.monotonic() - start
        assert elapsed < 1.0 + 0.8, f"the attempt took {elapsed:.1f} s"
        assert not outcome.ok and "deadline" in (outcome.error or ""), outcome.error
    finally:
        drip.stop()


def test_delivery_connects_to_the_checked_address_not_a_second_lookup(
    session_factory: sessionmaker[Session],
    sent_tasks: SentTasks,
    webhook_settings: None,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """DNS rebinding: the name answers 127.0.0.1 (allowed) while it is checked and then
    127.0.0.2 (not allowed: an internal service listens there). The attempt goes to the
    address that passed the check and sends the original Host header."""
    monkeypatch.setenv("TWINDELTA_WEBHOOK_ALLOWED_NETWORKS", '["127.0.0.1/32"]')
    get_settings.cache_clear()
    port = free_port()
    outside = Receiver(port=port, host="127.0.0.1").start()
    inside = Receiver(port=port, host="127.0.0.2").start()
    real_getaddrinfo = socket.getaddrinfo
    lookups: list[str] = []

    def rebinding(host: Any, *args: Any, **kwargs: Any) -> Any:
        if host == "hooks.rebind.test":
            lookups.append(host)  # the check at subscribe time and at delivery, then rebound
            host = "127.0.0.1" if len(lookups) <= 2 else "127.0.0.2"
        return real_getaddrinfo(host, *args, **kwargs)

    monkeypatch.setattr(socket, "getaddrinfo", rebinding)
    try:
        env = make_env(session_factory)
        _, secret = subscribe(session_factory, f"http://hooks.rebind.test:{port}/hook")
        record(session_factory, env)
        assert drive(session_factory, sent_tasks) == ["succeeded"]
        assert inside.on("/hook") == []
        [hit] = outside.on("/hook")
        assert hit.headers["host"] == f"hooks.rebind.test:{port}"
        webhooks.verify_signature(secret, hit.headers, hit.body)
        assert len(lookups) == 2  # one at subscribe time, one per attempt
    finally:
        outside.stop()
        inside.stop()


def test_proxy_environment_variables_are_ignored(
    session_factory: sessionmaker[Session],
    sent_tasks: SentTasks,
    webhook_settings: None,
    receiver: Receiver,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A proxy named in the environment (here a dead one) is not used: the attempt goes
    straight to the checked address (a proxy would also re-resolve the name itself)."""
    dead = f"http://127.0.0.1:{free_port()}"
    for name in ("HTTP_PROXY", "HTTPS_PROXY", "ALL_PROXY"):
        monkeypatch.setenv(name, dead)
        monkeypatch.setenv(name.lower(), dead)
    for name in ("NO_PROXY", "no_proxy"):
        monkeypatch.delenv(name, raising=False)
    env = make_env(session_factory)
    subscribe(session_factory, receiver.url())
    record(session_factory, env)
    assert drive(session_factory, sent_tasks) == ["succeeded"]
    assert len(receiver.on("/hook")) == 1


# --- secrets at rest and rotation -------------------------------------------------------------


def test_secret_encrypted_at_rest_with_a_generated_key_file(
    session_factory: sessionmaker[Session],
    sent_tasks: SentTasks,
    webhook_settings: None,
    data_dir: Path,
    receiver: Receiver,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The embedded default (no TWINDELTA_SECRET_KEY): a key file is made under the data
    folder, readable by the owner only; the row holds no trace of the secret; deliveries are
    still signed with it; another key cannot read it."""
    monkeypatch.delenv("TWINDELTA_SECRET_KEY", raising=False)
    get_settings.cache_clear()
    sub_id, secret = subscribe(session_factory, receiver.url())
    key_file = data_dir / "secret.key"
    assert key_file.exists() and stat.S_IMODE(key_file.stat().st_mode) == 0o600
    with session_factory() as s:
        row = s.execute(
            text("SELECT * FROM webhook_subscriptions WHERE id = :id"), {"id": sub_id}
        ).one()
    stored = " ".join(str(v) for v in row)
    raw = base64.b64decode(secret.removeprefix("whsec_"))
    for trace in (secret, secret.removeprefix("whsec_"), raw.hex(), "whsec_"):
        assert trace not in stored
    record(session_factory, make_env(session_factory))
    assert drive(session_factory, sent_tasks) == ["succeeded"]
    [hit] = receiver.on("/hook")
    webhooks.verify_signature(secret, hit.headers, hit.body)
    other = get_settings().model_copy(update={"secret_key": SecretStr("k" * 16 + "e" * 16 + "y")})
    with session_factory() as s:
        sub = s.get(WebhookSubscription, sub_id)
        assert sub is not None
        with pytest.raises(secretbox.SecretUnreadable):
            webhooks.current_secret(other, sub)


def test_settings_refuse_a_missing_or_placeholder_secret_key(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.delenv("TWINDELTA_SECRET_KEY", raising=False)
    monkeypatch.delenv("TWINDELTA_BROKER_URL", raising=False)
    with pytest.raises(ValidationError, match="TWINDELTA_SECRET_KEY is required"):
        Settings(broker_url="redis://127.0.0.1:6379/0")
    with pytest.raises(ValidationError, match="TWINDELTA_SECRET_KEY is required"):
        Settings(broker_url="redis://127.0.0.1:6379/0", secret_key="")
    for placeholder in ("changeme", "x" * 40, "change-me-to-a-long-random-string-please"):
        with pytest.raises(ValidationError, match="placeholder"):
            Settings(secret_key=placeholder)
    good = "3f9c1a7e5b2d48c6a0e1f7b9d3c5a8e2"
    assert Settings(broker_url="redis://127.0.0.1:6379/0", secret_key=good).secret_key
    assert Settings().secret_key is None  # embedded: the generated key file


def test_a_changed_secret_key_keeps_the_old_one_after_a_comma_then_reencrypts(
    session_factory: sessionmaker[Session], webhook_settings: None, monkeypatch: pytest.MonkeyPatch
) -> None:
    old_key, new_key = "a1b2c3d4e5f60718293a4b5c6d7e8f90", "0f1e2d3c4b5a69788796a5b4c3d2e1f0"
    monkeypatch.setenv("TWINDELTA_SECRET_KEY", old_key)
    get_settings.cache_clear()
    sub_id, secret = subscribe(session_factory, "http://127.0.0.1:9/hook")
    only_new = get_settings().model_copy(update={"secret_key": SecretStr(new_key)})

    def read(settings: Settings) -> str:
        with session_factory() as s:
            sub = s.get(WebhookSubscription, sub_id)
            assert sub is not None
            return webhooks.current_secret(settings, sub)

    with pytest.raises(secretbox.SecretUnreadable):
        read(only_new)
    monkeypatch.setenv("TWINDELTA_SECRET_KEY", f"{new_key},{old_key}")
    get_settings.cache_clear()
    assert read(get_settings()) == secret  # the old key still decrypts
    with db.transaction() as s:  # `twindelta reencrypt-secrets`
        assert webhooks.reencrypt_secrets(s, get_settings()) >= 1
    assert read(only_new) == secret  # the old key can go now


def test_rotated_secret_signs_with_both_during_the_overlap_then_only_the_new(
    session_factory: sessionmaker[Session],
    sent_tasks: SentTasks,
    webhook_settings: None,
    receiver: Receiver,
) -> None:
    env = make_env(session_factory)
    sub_id, old = subscribe(session_factory, receiver.url())
    before = utcnow()
    with session_factory.begin() as s:
        sub, new = webhooks.rotate_secret(s, get_settings(), sub_id)
        assert new != old and new.startswith("whsec_")
        expires = sub.previous_secret_expires_at
    assert expires is not None
    overlap = get_settings().webhook_secret_overlap_s
    assert abs((expires - before).total_seconds() - overlap) < 5
    event_id = record(session_factory, env, 1)
    assert drive(session_factory, sent_tasks) == ["succeeded"]
    [hit] = receiver.on("/hook")
    ts = int(hit.headers["webhook-timestamp"])
    signatures = hit.headers["webhook-signature"].split(" ")
    assert signatures == [
        webhooks.sign(new, event_id, ts, hit.body),
        webhooks.sign(old, event_id, ts, hit.body),
    ]
    webhooks.verify_signature(new, hit.headers, hit.body)  # a receiver already switched
    webhooks.verify_signature(old, hit.headers, hit.body)  # one not switched yet
    webhooks.verify_signature([webhooks.new_secret(), old], hit.headers, hit.body)
    with pytest.raises(webhooks.WebhookVerificationError):
        webhooks.verify_signature(webhooks.new_secret(), hit.headers, hit.body)

    with session_factory.begin() as s:  # the overlap is over
        got = s.get(WebhookSubscription, sub_id)
        assert got is not None
        got.previous_secret_expires_at = utcnow() - timedelta(seconds=1)
    record(session_factory, env, 2)
    assert drive(session_factory, sent_tasks) == ["succeeded"]
    last = receiver.on("/hook")[-1]
    assert len(last.headers["webhook-signature"].split(" ")) == 1
    webhooks.verify_signature(new, last.headers, last.body)
    with pytest.raises(webhooks.WebhookVerificationError):
        webhooks.verify_signature(old, last.headers, last.body)


def test_rotation_without_overlap_and_of_a_deactivated_webhook(
    session_factory: sessionmaker[Session], webhook_settings: None, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("TWINDELTA_WEBHOOK_SECRET_OVERLAP_S", "0")
    get_settings.cache_clear()
    sub_id, old = subscribe(session_factory, "http://127.0.0.1:9/hook")
    with session_factory.begin() as s:
        sub, new = webhooks.rotate_secret(s, get_settings(), sub_id)
        assert webhooks.signing_secrets(get_settings(), sub) == (new,) and new != old
        assert sub.previous_secret_encrypted is None
        webhooks.deactivate(s, sub_id)
        with pytest.raises(Conflict):
            webhooks.rotate_secret(s, get_settings(), sub_id)


def test_migration_encrypts_existing_plain_secrets_and_downgrade_restores_them(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """0003 on a database whose subscriptions hold plain whsec_ secrets (the embedded
    default, so the key file is generated under the data folder on the way)."""
    monkeypatch.setenv("TWINDELTA_DATA_DIR", str(tmp_path))
    monkeypatch.delenv("TWINDELTA_SECRET_KEY", raising=False)
    monkeypatch.delenv("TWINDELTA_BROKER_URL", raising=False)
    get_settings.cache_clear()
    url = f"sqlite:///{tmp_path / 'old.db'}"
    config = Config(str(REPO_ROOT / "alembic.ini"))
    config.attributes["url"] = url
    command.upgrade(config, "0002")
    secret = webhooks.new_secret()
    engine = db.make_engine(url)
    try:
        with engine.begin() as conn:
            conn.execute(
                text(
                    "INSERT INTO webhook_subscriptions (id, url, event_types, secret, active,"
                    " created_at) VALUES ('w1', 'https://93.184.216.34/h', '[]', :s, 1,"
                    " '2026-11-01 00:00:00')"
                ),
                {"s": secret},
            )
        command.upgrade(config, "0003")
        with engine.connect() as conn:
            stored = conn.execute(text("SELECT secret_encrypted FROM webhook_subscriptions")).one()
        assert stored[0] != secret and secret.removeprefix("whsec_") not in stored[0]
        assert secretbox.decrypt(get_settings(), stored[0]) == secret
        assert (tmp_path / "secret.key").exists()
        command.downgrade(config, "0002")
        with engine.connect() as conn:
            assert conn.execute(text("SELECT secret FROM webhook_subscriptions")).one()[0] == secret
    finally:
        engine.dispose()
        get_settings.cache_clear()


def make_tls(folder: Path, names: list[str]) -> tuple[Path, ssl.SSLContext, list[str]]:
    """A test CA (its PEM file) and a server context with a certificate for ``names``
    signed by it; the list collects the SNI names clients send."""
    key_usage = x509.KeyUsage(
        digital_signature=True,
        content_commitment=False,
        key_encipherment=False,
        data_encipherment=False,
        key_agreement=False,
        key_cert_sign=True,
        crl_sign=True,
        encipher_only=False,
        decipher_only=False,
    )
    now = datetime.now(UTC)
    ca_key, leaf_key = (
        ec.generate_private_key(ec.SECP256R1()),
        ec.generate_private_key(ec.SECP256R1()),
    )
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "twindelta test CA")])

    def builder(subject: x509.Name, public_key: Any) -> x509.CertificateBuilder:
        return (
            x509.CertificateBuilder()
            .subject_name(subject)
            .issuer_name(ca_name)
            .public_key(public_key)
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - timedelta(minutes=5))
            .not_valid_after(now + timedelta(days=1))
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(public_key), False)
            .add_extension(
                x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), False
            )
        )

    ca = (
        builder(ca_name, ca_key.public_key())
        .add_extension(x509.BasicConstraints(ca=True, path_length=None), True)
        .add_extension(key_usage, True)
        .sign(ca_key, hashes.SHA256())
    )
    leaf = (
        builder(
            x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, names[0])]), leaf_key.public_key()
        )
        .add_extension(x509.SubjectAlternativeName([x509.DNSName(n) for n in names]), False)
        .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH]), False)
        .sign(ca_key, hashes.SHA256())
    )
    ca_file, cert_file, key_file = folder / "ca.pem", folder / "leaf.pem", folder / "leaf.key"
    ca_file.write_bytes(ca.public_bytes(serialization.Encoding.PEM))
    cert_file.write_bytes(leaf.public_bytes(serialization.Encoding.PEM))
    key_file.write_bytes(
        leaf_key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption(),
        )
    )
    server = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    server.load_cert_chain(cert_file, key_file)
    sni: list[str] = []
    server.sni_callback = lambda _sock, name, _ctx: sni.append(name or "") or None
    return ca_file, server, sni


@pytest.mark.parametrize("cert_name", ["hooks.tls.test", "someone-else.test"])
def test_https_to_the_pinned_address_keeps_sni_and_certificate_checks_on_the_name(
    session_factory: sessionmaker[Session],
    sent_tasks: SentTasks,
    webhook_settings: None,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    cert_name: str,
) -> None:
    """The connection goes to the checked IP, but TLS is the name's: SNI carries it and the
    certificate must be valid for it (a certificate for another name is refused)."""
    ca_file, server_tls, sni = make_tls(tmp_path, [cert_name])
    receiver = Receiver(tls=server_tls).start()
    real_getaddrinfo = socket.getaddrinfo

    def resolver(host: Any, *args: Any, **kwargs: Any) -> Any:
        return real_getaddrinfo("127.0.0.1" if host == "hooks.tls.test" else host, *args, **kwargs)

    monkeypatch.setattr(socket, "getaddrinfo", resolver)
    monkeypatch.setenv("SSL_CERT_FILE", str(ca_file))
    webhooks.tls_context.cache_clear()
    try:
        env = make_env(session_factory)
        subscribe(session_factory, f"https://hooks.tls.test:{receiver.port}/hook")
        record(session_factory, env)
        [d] = deliveries(session_factory)
        result = deliver_once(d.id)
        [attempt] = attempts_of(session_factory, d.id)
        if cert_name == "hooks.tls.test":
            assert result == "succeeded", attempt.error
            [hit] = receiver.on("/hook")
            assert hit.headers["host"] == f"hooks.tls.test:{receiver.port}"
        else:
            assert result == "retrying" and receiver.on("/hook") == []
            assert "certificate" in (attempt.error or "").lower(), attempt.error
        assert sni == ["hooks.tls.test"]
    finally:
        receiver.stop()
        webhooks.tls_context.cache_clear()
