"""The twin is updated per environment in snapshot ``seq`` order, whatever order the jobs
finish in: automatic comparisons compare each snapshot with the newest earlier snapshot that
reconstructed, once every earlier snapshot is settled; a snapshot that failed is skipped on
the record; a failed comparison holds the chain (visibly) until it is retried.

The jobs run in this process with the production glue (claim → compute → persist) and the
fake pipeline of :mod:`tests.workers.fake_pipeline` in place of the geometry."""

from __future__ import annotations

import io
import threading
import uuid
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from alembic import command
from alembic.config import Config
from fastapi.testclient import TestClient
from PIL import Image
from sqlalchemy import Connection, MetaData, create_engine, func, select, text
from sqlalchemy.orm import Session, sessionmaker

from app.core import db, twin
from app.core.enums import JobKind, JobState
from app.core.models import Change, Comparison, Environment, Event, InstancePose, Job, Snapshot
from tests.app.conftest import Keys, SentTasks, create_pg_database, drop_pg_database, migrate
from tests.conftest import REPO_ROOT
from tests.workers import fake_pipeline
from workers import comparison as comparison_glue
from workers import snapshot as snapshot_glue
from workers.pipeline.errors import PipelineError

CLASSES = ["drill", "bowl", "mug"]
# The scenes of three captures: class → box centre x (the fake pose's x, metres).
SCENES: list[dict[str, float]] = [
    {"drill": 0.2, "bowl": 0.5},
    {"drill": 0.3, "bowl": 0.5, "mug": 0.7},
    {"drill": 0.4, "mug": 0.7},
]


@pytest.fixture(autouse=True)
def fake(monkeypatch: pytest.MonkeyPatch) -> None:
    fake_pipeline.install(monkeypatch.setattr)


def png(seed: int) -> bytes:
    pixels = np.random.default_rng(seed).integers(0, 255, (24, 32, 3), dtype=np.uint8)
    out = io.BytesIO()
    Image.fromarray(pixels).save(out, "PNG")
    return out.getvalue()


def make_env(client: TestClient, keys: Keys) -> str:
    r = client.post(
        "/v1/environments", json={"name": "cell-7", "classes": CLASSES}, headers=keys.headers()
    )
    assert r.status_code == 201, r.text
    env_id: str = r.json()["id"]
    return env_id


def upload(
    client: TestClient, keys: Keys, env_id: str, scene: dict[str, float], tag: str = "v"
) -> str:
    """Three images that all see ``scene``; returns the snapshot id."""
    labels = "".join(f"{CLASSES.index(n)} {x} 0.5 0.1 0.1\n" for n, x in scene.items())
    parts: list[tuple[str, tuple[str, bytes, str]]] = []
    for i in range(3):
        parts.append(("images", (f"{tag}{i}.png", png(i), "image/png")))
        parts.append(("detections", (f"{tag}{i}.txt", labels.encode(), "text/plain")))
    r = client.post(
        f"/v1/environments/{env_id}/snapshots", files=parts, headers=keys.headers("capture")
    )
    assert r.status_code == 202, r.text
    snap_id: str = r.json()["snapshot"]["id"]
    return snap_id


def snapshot_job(factory: sessionmaker[Session], snapshot_id: str) -> str:
    with factory() as s:
        job_id = s.scalar(select(Job.id).where(Job.snapshot_id == snapshot_id))
    assert job_id is not None
    return job_id


def queued_comparisons(factory: sessionmaker[Session]) -> list[tuple[int, str]]:
    """(after seq, job id) of every queued comparison job, highest seq first."""
    with factory() as s:
        rows = s.execute(
            select(Snapshot.seq, Job.id)
            .join(Comparison, Comparison.job_id == Job.id)
            .join(Snapshot, Snapshot.id == Comparison.after_id)
            .where(Job.kind == JobKind.comparison, Job.state == JobState.queued)
            .order_by(Snapshot.seq.desc())
        ).all()
    return [(seq, job_id) for seq, job_id in rows]


def run_comparisons_newest_first(factory: sessionmaker[Session]) -> list[int]:
    """Run queued comparison jobs, always the one of the newest snapshot first (the order
    two workers may well finish them in); returns the after-seqs in the order run."""
    ran: list[int] = []
    while queued := queued_comparisons(factory):
        seq, job_id = queued[0]
        assert comparison_glue.run(job_id) == "succeeded"
        ran.append(seq)
    return ran


def twin_events(factory: sessionmaker[Session], env_id: str) -> list[dict[str, Any]]:
    with factory() as s:
        events = s.scalars(
            select(Event)
            .where(Event.environment_id == env_id, Event.type.like("twin.%"))
            .order_by(Event.created_at)
        ).all()
        return [{"type": e.type, **e.data} for e in events]


def twin_scene(client: TestClient, keys: Keys, env_id: str) -> dict[str, float]:
    state = client.get(f"/v1/environments/{env_id}/state", headers=keys.headers("read")).json()
    return {o["object"]: o["pose"][0][3] for o in state["objects"]}


def automatic_pairs(client: TestClient, keys: Keys, env_id: str) -> list[tuple[int, int]]:
    read = keys.headers("read")
    seqs = {
        s["id"]: s["seq"]
        for s in client.get(f"/v1/environments/{env_id}/snapshots", headers=read).json()
    }
    comps = client.get(f"/v1/environments/{env_id}/comparisons", headers=read).json()
    return sorted((seqs[c["before"]], seqs[c["after"]]) for c in comps if c["automatic"])


def test_twin_follows_seq_order_when_snapshots_and_comparisons_finish_out_of_order(
    client: TestClient,
    keys: Keys,
    session_factory: sessionmaker[Session],
    sent_tasks: SentTasks,
) -> None:
    env_id = make_env(client, keys)
    snaps = [upload(client, keys, env_id, scene) for scene in SCENES]
    # seq 3 reconstructs before seq 2 (a requeued job, or two workers)
    for index in (0, 2, 1):
        assert snapshot_glue.run(snapshot_job(session_factory, snaps[index])) == "succeeded"
    ran = run_comparisons_newest_first(session_factory)

    assert ran == [2, 3]  # one at a time, in seq order
    assert automatic_pairs(client, keys, env_id) == [(1, 2), (2, 3)]
    assert twin_scene(client, keys, env_id) == SCENES[2]  # drill moved on, bowl gone, mug
    read = keys.headers("read")
    state = client.get(f"/v1/environments/{env_id}/state", headers=read).json()
    drill = next(o for o in state["objects"] if o["object"] == "drill")
    history = client.get(
        f"/v1/environments/{env_id}/objects/{drill['instance_id']}/history", headers=read
    ).json()
    assert [p["snapshot"] for p in history["poses"]] == [snaps[1], snaps[2]]
    assert [p["pose"][0][3] for p in history["poses"]] == [0.3, 0.4]

    env = client.get(f"/v1/environments/{env_id}", headers=read).json()
    assert env["twin"] == {
        "seq": 3,
        "snapshot": snaps[2],
        "status": "current",
        "waiting_for": None,
        "comparison": None,
    }
    assert state["twin"]["seq"] == 3
    comps = client.get(f"/v1/environments/{env_id}/comparisons", headers=read).json()
    applied = sorted((c["applied_at"], c["after"]) for c in comps)
    assert all(c["applied_to_twin"] for c in comps)
    assert [after for _, after in applied] == [snaps[1], snaps[2]]
    updates = [(e["type"], e["seq"], e["outcome"]) for e in twin_events(session_factory, env_id)]
    assert updates == [
        ("twin.updated", 1, "baseline"),
        ("twin.updated", 2, "applied"),
        ("twin.updated", 3, "applied"),
    ]
    got = [client.get(f"/v1/snapshots/{s}", headers=read).json()["twin_update"] for s in snaps]
    assert got == ["baseline", "applied", "applied"]


def test_a_snapshot_that_failed_is_skipped_on_the_record(
    client: TestClient,
    keys: Keys,
    session_factory: sessionmaker[Session],
    sent_tasks: SentTasks,
) -> None:
    env_id = make_env(client, keys)
    snaps = [
        upload(client, keys, env_id, SCENES[0]),
        upload(client, keys, env_id, SCENES[1], tag="fail-"),
        upload(client, keys, env_id, SCENES[2]),
    ]
    assert snapshot_glue.run(snapshot_job(session_factory, snaps[0])) == "succeeded"
    assert snapshot_glue.run(snapshot_job(session_factory, snaps[2])) == "succeeded"
    assert queued_comparisons(session_factory) == []  # seq 2 is not settled: wait for it
    assert snapshot_glue.run(snapshot_job(session_factory, snaps[1])) == "failed"

    assert run_comparisons_newest_first(session_factory) == [3]
    assert automatic_pairs(client, keys, env_id) == [(1, 3)]
    assert twin_scene(client, keys, env_id) == {"drill": 0.4, "mug": 0.7}
    read = keys.headers("read")
    assert client.get(f"/v1/snapshots/{snaps[1]}", headers=read).json()["twin_update"] == (
        "skipped"
    )
    updates = [(e["seq"], e["outcome"]) for e in twin_events(session_factory, env_id)]
    assert updates == [(1, "baseline"), (2, "skipped"), (3, "applied")]
    skipped = twin_events(session_factory, env_id)[1]
    assert skipped["snapshot"] == snaps[1] and skipped["reason"]["code"] == "FakeFailure"
    env = client.get(f"/v1/environments/{env_id}", headers=read).json()
    assert env["twin"]["seq"] == 3 and env["twin"]["status"] == "current"


def test_a_failed_comparison_blocks_the_chain_until_retried(
    client: TestClient,
    keys: Keys,
    session_factory: sessionmaker[Session],
    sent_tasks: SentTasks,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    env_id = make_env(client, keys)
    snaps = [upload(client, keys, env_id, scene) for scene in SCENES]
    for snap_id in snaps:
        assert snapshot_glue.run(snapshot_job(session_factory, snap_id)) == "succeeded"

    def broken(*_args: Any, **_kwargs: Any) -> Any:
        raise PipelineError("the disk went away", code="FakeFailure")

    monkeypatch.setattr(comparison_glue, "compare_snapshots", broken)
    [(seq, job_id)] = queued_comparisons(session_factory)
    assert seq == 2 and comparison_glue.run(job_id) == "failed"
    assert queued_comparisons(session_factory) == []  # seq 3 is not compared past the gap

    read = keys.headers("read")
    comps = client.get(f"/v1/environments/{env_id}/comparisons", headers=read).json()
    [failed] = comps
    assert failed["state"] == "failed" and failed["applied_to_twin"] is False
    env = client.get(f"/v1/environments/{env_id}", headers=read).json()
    assert env["twin"] == {
        "seq": 1,
        "snapshot": snaps[0],
        "status": "blocked",
        "waiting_for": snaps[1],
        "comparison": failed["id"],
    }
    blocked = twin_events(session_factory, env_id)[-1]
    assert blocked["type"] == "twin.blocked" and blocked["comparison"] == failed["id"]
    assert blocked["error"]["code"] == "FakeFailure"

    assert client.post("/v1/comparisons/nope/retry", headers=keys.headers()).status_code == 404
    assert client.post(f"/v1/comparisons/{failed['id']}/retry", headers=read).status_code == 403
    r = client.post(f"/v1/comparisons/{failed['id']}/retry", headers=keys.headers())
    assert r.status_code == 202, r.text
    retried = r.json()
    assert retried["state"] == "queued" and retried["job"] != failed["job"]
    assert r.headers["location"] == f"/v1/jobs/{retried['job']}"
    assert ("comparison.run", {"job_id": retried["job"]}) in sent_tasks.calls
    env = client.get(f"/v1/environments/{env_id}", headers=read).json()
    assert env["twin"]["status"] == "comparing"
    again = client.post(f"/v1/comparisons/{failed['id']}/retry", headers=keys.headers())
    assert again.status_code == 409 and again.json()["error"] == "ComparisonNotRetryable"

    fake_pipeline.install(monkeypatch.setattr)
    assert run_comparisons_newest_first(session_factory) == [2, 3]
    assert automatic_pairs(client, keys, env_id) == [(1, 2), (2, 3)]
    assert twin_scene(client, keys, env_id) == SCENES[2]
    env = client.get(f"/v1/environments/{env_id}", headers=read).json()
    assert env["twin"]["seq"] == 3 and env["twin"]["status"] == "current"
    done = client.post(f"/v1/comparisons/{failed['id']}/retry", headers=keys.headers())
    assert done.status_code == 409
    outcomes = [(e["type"], e.get("seq")) for e in twin_events(session_factory, env_id)]
    assert outcomes == [
        ("twin.updated", 1),
        ("twin.blocked", 2),
        ("twin.updated", 2),
        ("twin.updated", 3),
    ]


def test_a_comparison_that_cannot_succeed_is_left_behind_by_deleting_its_snapshot(
    client: TestClient,
    keys: Keys,
    session_factory: sessionmaker[Session],
    sent_tasks: SentTasks,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The way out of a comparison that fails whatever is retried: delete the snapshot it
    compares; the chain skips the deleted snapshot on the record and compares the next."""
    env_id = make_env(client, keys)
    snaps = [upload(client, keys, env_id, scene) for scene in SCENES]
    for snap_id in snaps:
        assert snapshot_glue.run(snapshot_job(session_factory, snap_id)) == "succeeded"

    def broken(*_args: Any, **_kwargs: Any) -> Any:
        raise PipelineError("this capture cannot be compared", code="FakeFailure")

    monkeypatch.setattr(comparison_glue, "compare_snapshots", broken)
    [(_seq, job_id)] = queued_comparisons(session_factory)
    assert comparison_glue.run(job_id) == "failed"
    read = keys.headers("read")
    assert client.get(f"/v1/environments/{env_id}", headers=read).json()["twin"]["status"] == (
        "blocked"
    )

    r = client.delete(f"/v1/snapshots/{snaps[1]}", headers=keys.headers())
    assert r.status_code == 204, r.text
    fake_pipeline.install(monkeypatch.setattr)
    assert run_comparisons_newest_first(session_factory) == [3]
    assert automatic_pairs(client, keys, env_id) == [(1, 3)]
    assert twin_scene(client, keys, env_id) == {"drill": 0.4, "mug": 0.7}
    updates = [
        (e["type"], e["seq"], e.get("outcome")) for e in twin_events(session_factory, env_id)
    ]
    assert updates == [
        ("twin.updated", 1, "baseline"),
        ("twin.blocked", 2, None),
        ("twin.updated", 2, "skipped"),
        ("twin.updated", 3, "applied"),
    ]
    env = client.get(f"/v1/environments/{env_id}", headers=read).json()
    assert env["twin"]["seq"] == 3 and env["twin"]["status"] == "current"


def test_migration_settles_existing_environments_up_to_their_first_unapplied_snapshot(
    tmp_path: Path,
) -> None:
    """0004 on a database that old code filled: each environment's twin is taken to have
    every snapshot of its longest settled run from seq 1, and the chain goes on from there."""
    url = f"sqlite:///{tmp_path / 'old.db'}"
    config = Config(str(REPO_ROOT / "alembic.ini"))
    config.attributes["url"] = url
    command.upgrade(config, "0003")
    engine = create_engine(url)
    meta = MetaData()
    meta.reflect(engine)
    now = datetime(2026, 11, 1, tzinfo=UTC)

    def insert(conn: Connection, table: str, **values: Any) -> None:
        """A row with ``values``; any other NOT NULL column gets a plain filler."""
        for column in meta.tables[table].columns:
            if column.name in values or column.nullable or column.server_default is not None:
                continue
            python_type = column.type.python_type
            filler: dict[type, Any] = {str: "x", int: 0, float: 0.0, bool: False, dict: {}}
            values[column.name] = now if python_type is datetime else filler.get(python_type, [])
        conn.execute(meta.tables[table].insert().values(**values))

    states = ["reconstructed", "failed", "reconstructed", "reconstructed", "uploaded"]
    with engine.begin() as conn:
        insert(conn, "environments", id="env-a", name="a", classes=[], options={})
        insert(conn, "environments", id="env-b", name="b", classes=[], options={})
        for seq, state in enumerate(states, start=1):
            insert(conn, "snapshots", id=f"s{seq}", environment_id="env-a", seq=seq, state=state)
        for name, before, after, applied in (("c3", "s1", "s3", True), ("c4", "s3", "s4", False)):
            insert(conn, "jobs", id=f"job-{name}", kind="comparison", state="succeeded")
            insert(
                conn,
                "comparisons",
                id=name,
                environment_id="env-a",
                before_id=before,
                after_id=after,
                job_id=f"job-{name}",
                automatic=True,
                state="succeeded" if applied else "queued",
                applied_to_state=applied,
                completed_at=now if applied else None,
            )
    command.upgrade(config, "0004")
    with engine.connect() as conn:
        envs = dict(
            conn.execute(
                text(
                    "SELECT id, twin_seq || ':' || coalesce(twin_snapshot_id, '-') "
                    "FROM environments"
                )
            ).all()
        )
        updates = dict(conn.execute(text("SELECT id, twin_update FROM snapshots")).all())
        applied_at = dict(conn.execute(text("SELECT id, applied_at FROM comparisons")).all())
    assert envs == {"env-a": "3:s3", "env-b": "0:-"}
    assert updates == {"s1": "baseline", "s2": "skipped", "s3": "applied", "s4": None, "s5": None}
    assert applied_at["c3"] is not None and applied_at["c4"] is None
    # and back: the columns go, the rows stay (no table is recreated, so nothing cascades)
    command.downgrade(config, "0003")
    with engine.connect() as conn:
        assert conn.execute(text("SELECT count(*) FROM snapshots")).scalar() == len(states)
        assert conn.execute(text("SELECT count(*) FROM comparisons")).scalar() == 2
        columns = {row[1] for row in conn.execute(text("PRAGMA table_info(environments)"))}
    engine.dispose()
    assert "twin_seq" not in columns


def test_two_transactions_never_apply_the_same_snapshot_twice() -> None:
    """PostgreSQL, two connections: while one transaction moves the twin on (the
    environment row locked), another one's advance waits for it, then finds nothing left
    to do: the comparison's changes are in the twin once, one twin.updated per snapshot."""
    name = f"twindelta_test_{uuid.uuid4().hex[:8]}"
    url = create_pg_database(name)
    try:
        migrate(url)
        engine = db.make_engine(url)
        factory = sessionmaker(bind=engine, expire_on_commit=False)
        with factory.begin() as s:
            env = Environment(name="race", classes=["drill"], options={})
            s.add(env)
            s.flush()
            snaps = [
                Snapshot(environment_id=env.id, seq=seq, state="reconstructed", storage_prefix="x")
                for seq in (1, 2)
            ]
            s.add_all(snaps)
            job = Job(kind=JobKind.comparison, task_name="comparison.run", state="succeeded")
            s.add(job)
            s.flush()
            comparison = Comparison(
                environment_id=env.id,
                before_id=snaps[0].id,
                after_id=snaps[1].id,
                job_id=job.id,
                automatic=True,
                state="succeeded",
            )
            comparison.changes.append(
                Change(position=0, type="added", object_name="drill", instance_id=str(uuid.uuid4()))
            )
            s.add(comparison)
            env.twin_seq, env.twin_snapshot_id = 1, snaps[0].id
        env_id = env.id

        first = factory()
        first.begin()
        assert twin.advance(first, env_id).seq == 2  # applied; not committed yet
        second_done = threading.Event()
        outcome: list[Any] = []

        def second() -> None:
            with factory.begin() as s:
                outcome.append(twin.advance(s, env_id))
            second_done.set()

        thread = threading.Thread(target=second)
        thread.start()
        assert not second_done.wait(1.0)  # held on the environment row
        first.commit()
        first.close()
        thread.join(10)
        assert second_done.is_set() and outcome[0].seq == 2
        with factory() as s:
            poses = s.scalar(select(func.count()).select_from(InstancePose))
            updates = s.scalars(
                select(Event.data).where(
                    Event.type == "twin.updated", Event.environment_id == env_id
                )
            ).all()
        assert poses == 1
        assert [u["seq"] for u in updates] == [2]
        engine.dispose()
    finally:
        drop_pg_database(name)
