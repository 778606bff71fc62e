"""Webhooks through real Celery workers (threads pool, embedded beat running the dispatcher)
over a private Redis, against a fresh PostgreSQL built by the migrations, to a real HTTP
receiver on loopback: a slow receiver does not delay another subscription, order is kept
per subscription, and a worker killed mid-schedule loses nothing (the event arrives exactly
once more, from a fresh worker that finds the schedule in the database).

One test, so the workers start twice in all (each start imports the whole worker)."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from datetime import timedelta
from pathlib import Path

import pytest
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from app.cli import worker_commands
from app.core import db, events, queue, webhooks
from app.core.enums import DeliveryState, EventType, JobKind, JobState
from app.core.models import Delivery, DeliveryAttempt, Environment, Job, WebhookSubscription, utcnow
from app.core.queue import CPU_QUEUE
from app.core.settings import get_settings
from tests.app.core.test_webhooks import DripServer, Receiver, overlapping
from tests.e2e.conftest import SECRET_KEY, Processes, RedisServer, wait_until

pytestmark = [pytest.mark.slow, pytest.mark.e2e, pytest.mark.postgres, pytest.mark.redis]

SCHEDULE = "[0.3, 10.0, 0.3]"


@pytest.fixture
def stack(
    tmp_path: Path,
    pg_url: str,
    redis_server: RedisServer,
    processes: Callable[..., Processes],
    monkeypatch: pytest.MonkeyPatch,
) -> Iterator[tuple[Processes, sessionmaker[Session]]]:
    """Worker settings, and this process set up as the API would be (same database and
    broker), so events recorded here are sent to the workers after commit."""
    settings = {
        "database_url": pg_url,
        "broker_url": redis_server.url,
        "webhook_retry_schedule_s": SCHEDULE,
        "webhook_allowed_networks": '["127.0.0.0/8"]',
        "webhook_timeout_s": "5",
        "secret_key": SECRET_KEY,  # API and workers must share it (secrets at rest)
    }
    procs = processes(**settings)
    for key, value in settings.items():
        monkeypatch.setenv(f"TWINDELTA_{key.upper()}", value)
    monkeypatch.setenv("TWINDELTA_DATA_DIR", str(tmp_path / "api-data"))
    get_settings.cache_clear()
    queue.get_sender.cache_clear()
    engine = db.make_engine(pg_url)
    factory = sessionmaker(bind=engine, expire_on_commit=False)
    db.use_session_factory(factory)
    yield procs, factory
    db.use_session_factory(None)
    engine.dispose()
    get_settings.cache_clear()
    queue.get_sender.cache_clear()


def start_worker(procs: Processes, name: str, tmp_path: Path) -> list[str]:
    """Every worker but the cpu one, with the command lines ``twindelta serve`` uses (the
    embedded layout under test); returns their process names."""
    data_dir = tmp_path / name
    data_dir.mkdir(exist_ok=True)
    names = []
    for i, argv in enumerate(worker_commands(data_dir, 1)):
        if argv[argv.index("-Q") + 1] != CPU_QUEUE:
            names.append(f"{name}-{i}")
            procs.start(names[-1], argv)
    return names


def subscribe(factory: sessionmaker[Session], url: str, types: list[EventType]) -> str:
    with factory.begin() as s:
        return webhooks.create_subscription(
            s, get_settings(), url=url, event_types=types, environment_id=None
        ).id


def make_env(factory: sessionmaker[Session]) -> str:
    with factory.begin() as s:
        env = Environment(name="line-1", classes=["power_drill"])
        s.add(env)
        s.flush()
        return env.id


def record(factory: sessionmaker[Session], env_id: str, n: int, event_type: EventType) -> str:
    with factory.begin() as s:
        return events.record(
            s, event_type, environment_id=env_id, subject=f"things/{n}", data={"n": n}
        ).id


def of(factory: sessionmaker[Session], sub_id: str) -> list[Delivery]:
    with factory() as s:
        query = select(Delivery).where(Delivery.subscription_id == sub_id)
        return list(s.scalars(query.order_by(Delivery.seq)))


def test_slow_receiver_order_and_worker_killed_mid_schedule(
    tmp_path: Path, stack: tuple[Processes, sessionmaker[Session]]
) -> None:
    procs, factory = stack
    receiver = Receiver().start()
    try:
        changes = [EventType.comparison_completed]
        slow = subscribe(factory, receiver.url("/slow"), changes)
        fast = subscribe(factory, receiver.url("/fast"), changes)
        flaky = subscribe(factory, receiver.url("/flaky"), [EventType.job_failed])
        gate = receiver.gate("/slow")  # the slow receiver hangs until the gate opens
        receiver.plan("/flaky", [500, 500])
        env = make_env(factory)
        wh1 = start_worker(procs, "wh1", tmp_path)
        failed_id = record(factory, env, 0, EventType.job_failed)
        ids = [record(factory, env, n, EventType.comparison_completed) for n in (1, 2, 3)]

        # a hanging receiver delays neither the other subscription nor its own order
        wait_until(lambda: len(receiver.on("/fast")) == 3, 30, "the fast receiver's three")
        time.sleep(0.5)
        assert len(receiver.on("/slow")) == 1  # the later two wait behind the hung first
        gate.set()
        wait_until(lambda: len(receiver.on("/slow")) == 3, 30, "the slow receiver's three")
        fast_hits, slow_hits = receiver.on("/fast"), receiver.on("/slow")
        assert [h.headers["webhook-id"] for h in fast_hits] == ids
        assert [h.headers["webhook-id"] for h in slow_hits] == ids
        assert slow_hits[1].at >= slow_hits[0].done_at  # the second waited for the first

        # the flaky receiver failed twice; its third attempt is 10 s away, in the database only
        wait_until(lambda: len(attempts(factory, flaky)) == 2, 30, "two failed attempts")
        for name in wh1:  # SIGKILL the workers, their threads and the embedded beat
            procs.kill(name)
        assert [h.status for h in receiver.on("/flaky")] == [500, 500]
        assert [d.state for d in of(factory, flaky)] == [DeliveryState.pending]

        start_worker(procs, "wh2", tmp_path)  # a fresh process picks up from the database
        wait_until(
            lambda: [d.state for d in of(factory, flaky)] == [DeliveryState.succeeded],
            40,
            "the flaky delivery to succeed",
        )
        time.sleep(1.0)  # and nothing more arrives
        hits = receiver.on("/flaky")
        assert [h.status for h in hits] == [500, 500, 200]
        assert {h.headers["webhook-id"] for h in hits} == {failed_id}
        assert [a.status_code for a in attempts(factory, flaky)] == [500, 500, 200]
        with factory() as s:
            sub = s.get(WebhookSubscription, flaky)
            assert sub is not None
            secret = webhooks.current_secret(get_settings(), sub)
        for h in hits:
            webhooks.verify_signature(secret, h.headers, h.body)
        for sub in (slow, fast):
            assert [d.state for d in of(factory, sub)] == [DeliveryState.succeeded] * 3
    finally:
        receiver.stop()


def attempts(factory: sessionmaker[Session], sub_id: str) -> list[DeliveryAttempt]:
    with factory() as s:
        query = (
            select(DeliveryAttempt)
            .join(Delivery, Delivery.id == DeliveryAttempt.delivery_id)
            .where(Delivery.subscription_id == sub_id)
            .order_by(DeliveryAttempt.number)
        )
        return list(s.scalars(query))


def test_drip_receivers_end_at_their_deadline_and_do_not_starve_dispatch_or_sweep(
    tmp_path: Path, stack: tuple[Processes, sessionmaker[Session]]
) -> None:
    """Four receivers answering one byte every 1.5 s take every delivery thread (4). Each
    attempt still ends at its 5 s deadline, no event is on two connections at once, and the
    dispatcher and the sweeper keep running meanwhile (they are not queued behind
    deliveries)."""
    procs, factory = stack
    drip = DripServer(interval_s=1.5, for_s=60.0).start()
    receiver = Receiver().start()
    try:
        changes = [EventType.comparison_completed]
        drips = [subscribe(factory, drip.url(f"/d{i}"), changes) for i in range(4)]
        probe = subscribe(factory, receiver.url("/probe"), [EventType.job_failed])
        env = make_env(factory)
        start_worker(procs, "wh", tmp_path)
        record(factory, env, 1, EventType.comparison_completed)
        wait_until(lambda: len(drip.open_now()) == 4, 60, "four deliveries hanging")

        # every delivery thread is taken: a lost deliver message and a lost job message
        # must still be found by the dispatcher and the sweeper
        record(factory, env, 2, EventType.job_failed)
        with factory.begin() as s:
            [probe_delivery] = s.scalars(select(Delivery).where(Delivery.subscription_id == probe))
            probe_delivery.dispatched_at = None  # its message is lost
            job = Job(
                kind=JobKind.snapshot,
                task_name="snapshot.process",
                state=JobState.queued,
                sends=1,
                enqueued_at=utcnow() - timedelta(hours=1),  # its message is lost too
            )
            s.add(job)
            s.flush()
            probe_id, job_id = probe_delivery.id, job.id

        def repaired() -> bool:
            with factory() as s:
                delivery, lost = s.get(Delivery, probe_id), s.get(Job, job_id)
                assert delivery is not None and lost is not None
                return delivery.dispatched_at is not None and lost.sends > 1

        wait_until(repaired, 3.5, "dispatch and sweep while every delivery thread hangs")
        assert len(drip.open_now()) == 4  # still hanging: they did not free a thread

        # each drip attempt ends at its deadline and is logged as such
        wait_until(lambda: len(drip_attempts(factory, drips)) >= 4, 15, "four attempts logged")
        for attempt in drip_attempts(factory, drips)[:4]:
            assert (attempt.error or "").startswith("deadline"), attempt.error
            assert attempt.latency_ms is not None and attempt.latency_ms < 5000 + 800
        closed = [c for c in drip.connections if c.closed_at is not None]
        assert len(closed) >= 4
        assert all(c.closed_at - c.opened_at < 5 + 1.0 for c in closed)  # type: ignore[operator]
        wait_until(
            lambda: [d.state for d in of(factory, probe)] == [DeliveryState.succeeded],
            30,
            "the probe delivery",
        )
        assert overlapping(drip.connections) == []  # never two connections for one event
        assert len({c.webhook_id for c in drip.connections}) == 1
    finally:
        drip.stop()
        receiver.stop()


def drip_attempts(factory: sessionmaker[Session], subs: list[str]) -> list[DeliveryAttempt]:
    with factory() as s:
        query = (
            select(DeliveryAttempt)
            .join(Delivery, Delivery.id == DeliveryAttempt.delivery_id)
            .where(Delivery.subscription_id.in_(subs))
            .order_by(DeliveryAttempt.attempted_at)
        )
        return list(s.scalars(query))
