"""Several worker hosts sharing nothing but PostgreSQL, Redis and the bucket: the real
pipeline on small generated scenes, two CPU workers each with its own private folder, one of
them killed mid-job, and every environment's twin still brought forward in ``seq`` order.

Processes (all on loopback): a database built by the migrations, a private redis-server, an
S3 emulator (moto's server in a thread of the test process: not a real object store), the
API, a maintenance host (the sweeper on Celery beat) and the CPU workers. Each process has
its own data and scratch folders; no folder is shared.

The story, in one test (the real pipeline is too slow for one test per property):
1. the library objects of the scenes are prepared;
2. environment A's two snapshots are uploaded; once both reconstruct on different workers,
   the worker of A's first snapshot is killed (SIGKILL) mid-job. The other worker finishes
   A's second snapshot first, then the first once the sweeper has put it back in the queue:
   A's later snapshot is reconstructed before its earlier one, for real;
3. a replacement worker host joins and environment B is uploaded; it runs beside A.
Then: every comparison finds its scene's change (type, object) and claims no other (a
cluster it leaves unidentified is no claim), the killed job ran exactly once to the end,
A's twin took its first snapshot as baseline and the comparison 1 → 2 was made only after
snapshot 1 was settled, jobs of different environments overlapped in time, every worker
took jobs, and no snapshot file lies in any host's own folders outside its scratch cache.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass
from datetime import datetime
from functools import partial
from pathlib import Path
from typing import Any

import httpx
import pytest
from sqlalchemy import create_engine, text

from app.client import free_port, upload_capture
from bench.loopback import generate_world
from tests.e2e.conftest import (
    Processes,
    RedisServer,
    api_client,
    poll_job,
    wait_until,
    worker_ready,
)
from workers.demo.evaluate import match_changes
from workers.pipeline.synth import builtin_models
from workers.pipeline.synth.shapes import write_model_ply

# four real reconstructions: minutes on a loaded 2-core machine, past the suite's 300 s default
pytestmark = [
    pytest.mark.slow,
    pytest.mark.e2e,
    pytest.mark.postgres,
    pytest.mark.redis,
    pytest.mark.timeout(900),
]

# (environment, scenario, seed): one before/after world each, 16 views of 640×480 (the full
# flow's size), the default presets.
WORLDS = [("A", "moved", 1), ("B", "removed", 2)]
VIEWS, WIDTH, HEIGHT, FOCAL_PX = 16, 640, 480, 520.0
# A job whose heartbeat is older than this goes back to the queue (the sweeper runs every
# second); long enough for a busy 2-core machine, short enough for the test.
HEARTBEAT_TIMEOUT_S = 8
RECONSTRUCT_S = 240  # the most one snapshot may take here, queue wait included


def _generate(args: tuple[Path, str, int]) -> Path:
    out, scenario, seed = args
    return generate_world(out, scenario, seed, VIEWS, (WIDTH, HEIGHT), FOCAL_PX)


@pytest.fixture
def worlds(tmp_path: Path) -> Iterator[dict[str, Future[Path]]]:
    """Environment name → its world (before/, after/, ground_truth.json) being generated in
    one background process, A first, while the services start and the library is prepared."""
    with ProcessPoolExecutor(max_workers=1) as pool:
        yield {
            name: pool.submit(_generate, (tmp_path / "worlds" / name, scenario, seed))
            for name, scenario, seed in WORLDS
        }


@dataclass
class Cluster:
    """The shared services and the hosts started on them; each host has a private folder."""

    tmp_path: Path
    make: Callable[..., Processes]
    shared: dict[str, str]
    hosts: dict[str, Processes]

    def host(self, name: str) -> Processes:
        folder = self.tmp_path / "hosts" / name
        folder.mkdir(parents=True)
        procs = self.make(
            scratch_dir=str(folder / "scratch"),
            heartbeat_interval_s="1",
            heartbeat_timeout_s=str(HEARTBEAT_TIMEOUT_S),
            requeue_after_s="30",  # lost messages only: fewer duplicate sends in the logs
            **self.shared,
        )
        procs.env["TWINDELTA_DATA_DIR"] = str(folder / "data")
        self.hosts[name] = procs
        return procs

    def workers(self, *names: str) -> None:
        """One CPU worker host per name, started together; returns once every one is ready."""
        for name in names:
            self.host(name).worker(name, "cpu")
        for name in names:
            log = self.tmp_path / f"{name}.log"
            wait_until(partial(worker_ready, log), 120, f"worker {name}")


@pytest.fixture
def cluster(
    tmp_path: Path,
    pg_url: str,
    redis_server: RedisServer,
    s3_storage_url: tuple[str, str],
    processes: Callable[..., Processes],
) -> Cluster:
    storage_url, endpoint = s3_storage_url
    shared = {
        "database_url": pg_url,
        "broker_url": redis_server.url,
        "storage_url": storage_url,
        "s3_endpoint_url": endpoint,
    }
    return Cluster(tmp_path, processes, shared, {})


def rows(url: str, sql: str, **params: Any) -> list[dict[str, Any]]:
    engine = create_engine(url)
    try:
        with engine.connect() as conn:
            return [dict(r._mapping) for r in conn.execute(text(sql), params)]
    finally:
        engine.dispose()


def job_row(url: str, **where: str) -> dict[str, Any]:
    ((column, value),) = where.items()
    (row,) = rows(url, f"SELECT * FROM jobs WHERE {column} = :v", v=value)
    return row


def pool_parent(worker: str) -> int:
    """The Celery parent process of the pool child named ``host:pid`` (runner.worker_name)."""
    pid = int(worker.rsplit(":", 1)[1])
    stat = Path(f"/proc/{pid}/stat").read_text()
    return int(stat.rsplit(")", 1)[1].split()[1])


def test_two_worker_hosts_real_pipeline_kill_and_seq_order(
    tmp_path: Path, pg_url: str, worlds: dict[str, Future[Path]], cluster: Cluster
) -> None:
    api = cluster.host("api")
    port = free_port()
    api.api(port)
    maintenance = cluster.host("maintenance")
    maintenance.worker("beat", "maintenance", "-B", "-s", str(tmp_path / "beat-schedule"))
    cluster.workers("w1", "w2")
    client = api_client(port)
    client.timeout = httpx.Timeout(120)

    # 1. the library: every object the scenes are made of, prepared by the workers
    classes = []
    object_jobs = []
    for model in builtin_models():
        path = tmp_path / "library" / f"{model.name}.ply"
        write_model_ply(model, path)
        files = {"file": (path.name, path.read_bytes())}
        r = client.post("/v1/objects", files=files, data={"name": model.name})
        assert r.status_code == 202, r.text
        classes.append(model.name)
        object_jobs.append(r.json()["job"]["id"])
    for job_id in object_jobs:
        assert poll_job(client, job_id, 180)["state"] == "succeeded"

    # 2. A's two snapshots on the two workers; the worker of the first is killed mid-job
    envs: dict[str, str] = {}
    truth: dict[str, dict[str, Any]] = {}
    snaps: dict[tuple[str, int], str] = {}

    def upload(env: str) -> None:
        """Environment ``env`` made for its world, then its before and after captures."""
        world = worlds[env].result(timeout=300)
        truth[env] = json.loads((world / "ground_truth.json").read_text())
        assert truth[env]["classes"] == classes
        reference = json.loads((world / "reference.json").read_text())
        body = {"name": f"cell-{env}", "classes": classes, "reference": reference}
        r = client.post("/v1/environments", json=body)
        assert r.status_code == 201, r.text
        envs[env] = r.json()["id"]
        for seq, capture in ((1, "before"), (2, "after")):
            accepted = upload_capture(client, envs[env], world / capture)
            snaps[env, seq] = accepted["snapshot"]["id"]

    upload("A")

    def a1() -> dict[str, Any]:
        return job_row(pg_url, snapshot_id=snaps["A", 1])

    def a2() -> dict[str, Any]:
        return job_row(pg_url, snapshot_id=snaps["A", 2])

    wait_until(
        lambda: a1()["state"] == a2()["state"] == "running" and a1()["progress"] >= 0.15,
        RECONSTRUCT_S,
        "A's snapshots running, the first past 15 %",
        every_s=0.2,
    )
    killed = a1()
    assert killed["worker"] != a2()["worker"] and killed["attempts"] == 1
    parent = pool_parent(killed["worker"])
    victim = next(
        n for n, h in cluster.hosts.items() if any(p.pid == parent for p in h.procs.values())
    )
    cluster.hosts[victim].kill(victim)
    survivor = a2()["worker"]

    # the sweeper puts A1 back; the survivor takes it once A2 is done
    wait_until(
        lambda: a1()["attempts"] == 2 and a1()["state"] in ("running", "succeeded"),
        RECONSTRUCT_S,
        "A's first snapshot taken again",
        every_s=0.2,
    )
    assert a1()["worker"] == survivor

    # 3. a replacement host joins; B runs beside A
    cluster.workers("w3")
    upload("B")

    comparisons: dict[str, dict[str, Any]] = {}

    def compared(env: str) -> bool:
        listed = client.get(f"/v1/environments/{envs[env]}/comparisons").json()
        final = [c for c in listed if c["state"] in ("succeeded", "failed", "cancelled")]
        if final:
            comparisons[env] = client.get(f"/v1/comparisons/{final[0]['id']}").json()
        return bool(final)

    for env in envs:
        wait_until(partial(compared, env), 3 * RECONSTRUCT_S, f"{env}'s comparison", 0.5)

    # every snapshot reconstructed, every comparison right against its scene's truth
    for (env, seq), snap_id in snaps.items():
        snap = client.get(f"/v1/snapshots/{snap_id}").json()
        assert snap["state"] == "reconstructed", (env, seq, snap)
    for env, comparison in comparisons.items():
        assert comparison["state"] == "succeeded", comparison
        assert comparison["before"] == snaps[env, 1] and comparison["after"] == snaps[env, 2]
        matches, extra = match_changes(truth[env], comparison["changes"])
        found = [(c["type"], c.get("object")) for c in comparison["changes"]]
        assert all(m.found is not None for m in matches), (env, truth[env]["changes"], found)
        # no false claim; a cluster the service flags without naming an object is not one
        assert all(c["type"] == "unidentified" for c in extra), (env, found)

    # the killed job: two attempts, the second by the surviving worker, one result
    job = a1()
    assert (job["state"], job["attempts"], job["worker"]) == ("succeeded", 2, survivor)
    reconstructed = rows(
        pg_url,
        "SELECT subject FROM events WHERE type = 'snapshot.reconstructed' AND environment_id = :e",
        e=envs["A"],
    )
    assert sorted(r["subject"] for r in reconstructed) == sorted(
        f"snapshots/{snaps['A', seq]}" for seq in (1, 2)
    )
    all_comparisons = client.get(f"/v1/environments/{envs['A']}/comparisons").json()
    assert len(all_comparisons) == 1

    # A's order: snapshot 2 reconstructed first, yet the twin started from snapshot 1 and
    # the comparison 1 → 2 was made only once snapshot 1 was settled
    s1, s2 = (client.get(f"/v1/snapshots/{snaps['A', seq]}").json() for seq in (1, 2))
    assert s2["reconstructed_at"] < s1["reconstructed_at"]
    comparison_created = rows(
        pg_url, "SELECT created_at FROM comparisons WHERE id = :c", c=comparisons["A"]["id"]
    )[0]["created_at"]
    assert comparison_created >= datetime.fromisoformat(s1["reconstructed_at"])
    updates = rows(
        pg_url,
        "SELECT data FROM events WHERE type = 'twin.updated' AND environment_id = :e "
        "ORDER BY created_at",
        e=envs["A"],
    )
    assert [u["data"]["seq"] for u in updates] == [1, 2], updates
    for env in envs:
        body = client.get(f"/v1/environments/{envs[env]}").json()
        assert body["twin"]["seq"] == 2 and body["twin"]["status"] == "current", body

    # every worker took jobs; jobs of different environments ran at the same time
    jobs = rows(pg_url, "SELECT * FROM jobs WHERE state = 'succeeded'")
    workers = {j["worker"] for j in jobs}  # w1 and w2 before the kill, the survivor, w3
    assert len(workers) >= 3 and {killed["worker"], survivor} <= workers, workers
    env_jobs = [j for j in jobs if j["environment_id"]]
    assert any(
        a["environment_id"] != b["environment_id"]
        and a["started_at"] < b["finished_at"]
        and b["started_at"] < a["finished_at"]
        for a in env_jobs
        for b in env_jobs
    )
    # nothing of a snapshot lies in a host's own folders outside its read cache, and only
    # the killed attempt left a work folder behind (on its dead host)
    for name in cluster.hosts:
        root = tmp_path / "hosts" / name
        held = [p for p in root.rglob("*") if p.is_file()]
        named = [p for p in held if any(s in p.as_posix() for s in snaps.values())]
        assert all(root / "scratch" / "cache" in p.parents for p in named), (name, named)
        work = root / "scratch" / "local" / ".work"
        left = sorted(p.name for p in work.iterdir()) if work.exists() else []
        assert left == ([killed["id"]] if name == victim else []), (name, left)
    print(
        "jobs:",
        [
            (j["kind"], j["worker"], round((j["finished_at"] - j["started_at"]).total_seconds(), 1))
            for j in sorted(jobs, key=lambda j: j["started_at"])
        ],
    )
