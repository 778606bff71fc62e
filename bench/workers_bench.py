"""Snapshot throughput of one worker against two (issue #22), on the same queue of jobs.

    python -m bench.workers_bench [--runs 3] [--quick] [--out bench/results/workers.json]

The queue: 6 snapshots over 3 environments (one generated before/after world each, 16
views of 640×480, the default presets), queued while no worker runs; their 3
automatic comparisons join the queue as the snapshots settle. Every job runs the real
pipeline. Configurations: 1 CPU worker pinned to core 0, and 2 CPU workers pinned to cores
0 and 1 (``taskset -c <core> celery worker -c 1``), so the ratio means something on a
2-core machine. Per run everything is fresh: a PostgreSQL database built by the migrations
(the local server), a private redis-server, a bucket in moto's S3 emulator on loopback (an
emulator: its bandwidth is not a real bucket's), and private data/scratch folders per
process; only PostgreSQL, Redis and the bucket are shared.

Measured per run: the drain time (first job started → last job finished, from the job rows),
jobs and snapshots per minute, each job's time in each stage (the job rows sampled every
0.2 s), the database's connections (max seen) and committed transactions per job, and the
bucket's bytes per snapshot (inputs, outputs, clouds read by the comparison). After the runs
the storage transfer of one snapshot job (fetching its inputs into an empty scratch cache,
putting its cloud back) is timed alone with the storage class the workers use. The library
objects are prepared before the queue is filled (not measured). Timings depend on the load
of the machine (recorded before and after).
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import shutil
import signal
import statistics
import subprocess
import sys
import time
from collections import defaultdict
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx

from app.client import REPO_ROOT, check, free_port, poll_job, upload_capture
from bench.loopback import (
    TEST_CREDENTIALS,
    create_bucket,
    drop_bucket,
    generate_world,
    redis_command,
    start_s3_server,
)
from bench.loopback import client as s3_client

KEY = "td_bench_admin_key_0123456789abcdef"
SECRET = "td_bench_secret_key_0123456789abcdefghijklmnop"
PG_ADMIN = "postgresql+psycopg://postgres@127.0.0.1:5432/postgres"
WORLDS = [("A", "moved", 1), ("B", "removed", 2), ("C", "added", 3)]
VIEWS, WIDTH, HEIGHT, FOCAL_PX = 16, 640, 480, 520.0
CONFIGS = {"1 worker": ["0"], "2 workers": ["0", "1"]}
SAMPLE_S = 0.2
TMP = Path(os.environ.get("TWINDELTA_BENCH_TMP", "/tmp/twindelta_bench")) / "workers"


def _generate(args: tuple[Path, str, int]) -> Path:
    out, scenario, seed = args
    if (out / "ground_truth.json").exists():
        return out
    return generate_world(out, scenario, seed, VIEWS, (WIDTH, HEIGHT), FOCAL_PX)


def worlds() -> dict[str, Path]:
    """Environment name → generated world (made once under TMP, reused)."""
    root = TMP / f"worlds-{VIEWS}x{WIDTH}x{HEIGHT}"
    jobs = [(root / name, scenario, seed) for name, scenario, seed in WORLDS]
    with ProcessPoolExecutor(max_workers=2) as pool:
        made = list(pool.map(_generate, jobs))
    return {name: path for (name, _, _), path in zip(WORLDS, made, strict=True)}


@dataclass
class Services:
    """One run's shared services and the processes started on them."""

    root: Path
    db_url: str
    db_name: str
    redis_url: str
    s3_endpoint: str
    bucket: str
    procs: dict[str, subprocess.Popen[bytes]] = field(default_factory=dict)

    def env(self, host: str) -> dict[str, str]:
        folder = self.root / host
        env = {k: v for k, v in os.environ.items() if not k.startswith("TWINDELTA_")}
        env.update(
            TEST_CREDENTIALS,
            TWINDELTA_DATA_DIR=str(folder / "data"),
            TWINDELTA_SCRATCH_DIR=str(folder / "scratch"),
            TWINDELTA_DATABASE_URL=self.db_url,
            TWINDELTA_BROKER_URL=self.redis_url,
            TWINDELTA_STORAGE_URL=f"s3://{self.bucket}/twindelta",
            TWINDELTA_S3_ENDPOINT_URL=self.s3_endpoint,
            TWINDELTA_BOOTSTRAP_ADMIN_KEY=KEY,
            TWINDELTA_SECRET_KEY=SECRET,
            PYTHONUNBUFFERED="1",
        )
        return env

    def start(self, name: str, argv: list[str]) -> None:
        log = (self.root / f"{name}.log").open("ab")
        self.procs[name] = subprocess.Popen(
            argv,
            env=self.env(name),
            cwd=REPO_ROOT,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )

    def stop(self, name: str) -> None:
        proc = self.procs.pop(name)
        try:
            os.killpg(proc.pid, signal.SIGTERM)
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=10)
        except ProcessLookupError:
            pass

    def workers(self, cores: list[str], tag: str) -> list[str]:
        """Start one CPU worker per core (pinned, concurrency 1); their names once ready."""
        names = [f"{tag}-cpu{core}" for core in cores]
        for name, core in zip(names, cores, strict=True):
            argv = [sys.executable, "-m", "celery", "-A", "workers.celery_app", "worker"]
            argv += ["-Q", "cpu", "-c", "1", "-n", f"{name}@%h", "--loglevel", "INFO"]
            self.start(name, ["taskset", "-c", core, *argv])
        for name in names:
            log = self.root / f"{name}.log"
            _wait(lambda log=log: log.exists() and " ready." in log.read_text(), 120, name)
        return names


def _wait(check_fn: Any, timeout_s: float, what: str, every_s: float = 0.2) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if check_fn():
            return
        time.sleep(every_s)
    raise TimeoutError(f"timed out after {timeout_s} s waiting for {what}")


def _sql(url: str, sql: str, **params: Any) -> list[dict[str, Any]]:
    from sqlalchemy import create_engine, text

    engine = create_engine(url, isolation_level="AUTOCOMMIT")
    try:
        with engine.connect() as conn:
            result = conn.execute(text(sql), params)
            return [dict(r._mapping) for r in result] if result.returns_rows else []
    finally:
        engine.dispose()


@contextmanager
def services(root: Path) -> Iterator[Services]:
    """A fresh database, redis-server and bucket in an S3 emulator; all removed after."""
    db_name = f"twindelta_bench_workers_{os.getpid()}"
    _sql(PG_ADMIN, f'DROP DATABASE IF EXISTS "{db_name}" WITH (FORCE)')
    _sql(PG_ADMIN, f'CREATE DATABASE "{db_name}"')
    db_url = PG_ADMIN.rsplit("/", 1)[0] + f"/{db_name}"
    redis_port = free_port()
    redis = subprocess.Popen(
        redis_command("redis-server", redis_port, root), stdout=subprocess.DEVNULL
    )
    endpoint, stop_s3 = start_s3_server()
    bucket = create_bucket(endpoint)
    svc = Services(root, db_url, db_name, f"redis://127.0.0.1:{redis_port}/0", endpoint, bucket)
    try:
        env = svc.env("migrate")
        subprocess.run(
            [sys.executable, "-m", "app.cli", "migrate"], env=env, cwd=REPO_ROOT, check=True
        )
        yield svc
    finally:
        for name in list(svc.procs):
            svc.stop(name)
        redis.terminate()
        redis.wait(timeout=10)
        # moto keeps buckets in this process's memory from one server to the next: drop it
        drop_bucket(endpoint, bucket)
        stop_s3()
        _sql(PG_ADMIN, f'DROP DATABASE IF EXISTS "{db_name}" WITH (FORCE)')


def _client(port: int) -> httpx.Client:
    client = httpx.Client(
        base_url=f"http://127.0.0.1:{port}",
        headers={"Authorization": f"Bearer {KEY}"},
        timeout=120,
    )

    def up() -> bool:
        try:
            return client.get("/readyz").status_code == 200
        except httpx.TransportError:
            return False

    _wait(up, 60, "the API")
    return client


def prepare(svc: Services, client: httpx.Client, scenes: dict[str, Path], cores: list[str]) -> None:
    """The library objects, prepared by the workers of this configuration, then stopped."""
    names = svc.workers(cores, "prep")
    jobs = []
    for path in sorted((scenes["A"] / "objects").glob("*.ply")):
        files = {"file": (path.name, path.read_bytes())}
        body = check(client.post("/v1/objects", files=files, data={"name": path.stem}), 202)
        jobs.append(body["job"]["id"])
    for job_id in jobs:
        assert poll_job(client, job_id, "object", 300, quiet=True)["state"] == "succeeded"
    for name in names:
        svc.stop(name)


def fill_queue(client: httpx.Client, scenes: dict[str, Path]) -> dict[str, list[str]]:
    """Environment name → its snapshot ids (seq order), all queued."""
    snaps: dict[str, list[str]] = {}
    for env_name, world in scenes.items():
        truth = json.loads((world / "ground_truth.json").read_text())
        env = check(
            client.post(
                "/v1/environments",
                json={
                    "name": f"bench-{env_name}",
                    "classes": truth["classes"],
                    "reference": json.loads((world / "reference.json").read_text()),
                },
            ),
            201,
        )
        snaps[env_name] = [
            upload_capture(client, env["id"], world / capture)["snapshot"]["id"]
            for capture in ("before", "after")
        ]
    return snaps


class Probe:
    """One AUTOCOMMIT connection to the run's database for every sample, so its own
    transactions are exactly one per query (``queries``) and its connection is known."""

    def __init__(self, svc: Services) -> None:
        from sqlalchemy import create_engine

        self.svc = svc
        self.engine = create_engine(svc.db_url, isolation_level="AUTOCOMMIT")
        self.conn = self.engine.connect()
        self.queries = 0

    def rows(self, sql: str, **params: Any) -> list[dict[str, Any]]:
        from sqlalchemy import text

        self.queries += 1
        return [dict(r._mapping) for r in self.conn.execute(text(sql), params)]

    def connections(self) -> int:
        """Connections to the run's database, this one's aside."""
        sql = (
            "SELECT count(*) AS n FROM pg_stat_activity WHERE datname = :d "
            "AND pid <> pg_backend_pid()"
        )
        return int(self.rows(sql, d=self.svc.db_name)[0]["n"])

    def commits(self) -> int:
        sql = "SELECT xact_commit FROM pg_stat_database WHERE datname = :d"
        return int(self.rows(sql, d=self.svc.db_name)[0]["xact_commit"])

    def close(self) -> None:
        self.conn.close()
        self.engine.dispose()


def drain(probe: Probe, n_snapshots: int) -> dict[str, Any]:
    """Sample the job rows and the database's connections until every snapshot job and
    every automatic comparison is final; returns the samples."""
    stages: dict[str, list[tuple[float, str]]] = defaultdict(list)
    connections: list[int] = []
    final = ("succeeded", "failed", "cancelled")
    deadline = time.monotonic() + 3600
    while time.monotonic() < deadline:
        now = time.monotonic()
        jobs = probe.rows("SELECT id, kind, state, stage FROM jobs WHERE kind <> 'object'")
        for job in jobs:
            if job["state"] == "running":
                stages[job["id"]].append((now, job["stage"] or "starting"))
        connections.append(probe.connections())
        snapshot_jobs = [j for j in jobs if j["kind"] == "snapshot"]
        comparison_jobs = [j for j in jobs if j["kind"] == "comparison"]
        if (
            len(snapshot_jobs) == n_snapshots
            and all(j["state"] in final for j in snapshot_jobs)
            and len(comparison_jobs) == n_snapshots // 2
            and all(j["state"] in final for j in comparison_jobs)
        ):
            break
        time.sleep(SAMPLE_S)
    return {"stages": stages, "connections": connections}


def stage_seconds(samples: list[tuple[float, str]]) -> dict[str, float]:
    """Seconds in each stage of one job, from its samples (each sample counts until the next)."""
    out: dict[str, float] = defaultdict(float)
    for (t0, stage), (t1, _) in itertools.pairwise(samples):
        out[stage] += t1 - t0
    return {k: round(v, 2) for k, v in out.items()}


def bucket_bytes(svc: Services, snaps: dict[str, list[str]]) -> dict[str, Any]:
    """Bytes in the bucket per snapshot: its inputs (images, labels, cameras) and what the
    workers wrote (reconstruction, comparison clusters)."""
    s3 = s3_client(svc.s3_endpoint)
    sizes: dict[str, int] = {}
    for page in s3.get_paginator("list_objects_v2").paginate(Bucket=svc.bucket):
        for item in page.get("Contents", ()):
            sizes[item["Key"]] = item["Size"]
    per: list[dict[str, int]] = []
    for ids in snaps.values():
        for snap_id in ids:
            mine = {k: v for k, v in sizes.items() if f"/snapshots/{snap_id}/" in k}
            outputs = sum(v for k, v in mine.items() if "/reconstruction/" in k)
            clusters = sum(v for k, v in mine.items() if "/comparisons/" in k or "cluster" in k)
            per.append(
                {
                    "inputs": sum(mine.values()) - outputs - clusters,
                    "outputs": outputs,
                    "comparison_outputs": clusters,
                    "cloud": sum(v for k, v in mine.items() if k.endswith("cloud.ply")),
                }
            )
    library = sum(v for k, v in sizes.items() if "/objects/" in k)
    folders: dict[str, int] = defaultdict(int)
    for key, size in sizes.items():
        folders[key.split("/")[1]] += size  # below the storage prefix
    return {
        "by_folder": dict(folders),
        "per_snapshot_mean": {k: round(statistics.mean(p[k] for p in per)) for k in per[0]},
        "library_objects_total": library,
        "bucket_total": sum(sizes.values()),
    }


def correctness(client: httpx.Client, scenes: dict[str, Path], snaps: dict[str, list[str]]) -> Any:
    """Per environment: the scene's true changes found by (type, object), the false ones
    (a type or object the truth does not have) and the clusters left unidentified."""
    from workers.demo.evaluate import match_changes

    out = {}
    for env_name, ids in snaps.items():
        after = check(client.get(f"/v1/snapshots/{ids[1]}"), 200)
        comparison = check(client.get(f"/v1/comparisons/{after['comparison']}"), 200)
        truth = json.loads((scenes[env_name] / "ground_truth.json").read_text())
        matches, extra = match_changes(truth, comparison["changes"])
        out[env_name] = {
            "state": comparison["state"],
            "true": len(matches),
            "found": sum(m.found is not None for m in matches),
            "false": sum(c["type"] != "unidentified" for c in extra),
            "unidentified": sum(c["type"] == "unidentified" for c in extra),
        }
    return out


def one_run(config: str, cores: list[str], scenes: dict[str, Path], run: int) -> dict[str, Any]:
    root = TMP / f"run-{config.replace(' ', '')}-{run}"
    shutil.rmtree(root, ignore_errors=True)
    root.mkdir(parents=True)
    with services(root) as svc:
        port = free_port()
        argv = [sys.executable, "-m", "uvicorn", "app.main:create_app", "--factory"]
        svc.start("api", [*argv, "--port", str(port), "--log-level", "warning"])
        client = _client(port)
        prepare(svc, client, scenes, cores)
        snaps = fill_queue(client, scenes)
        probe = Probe(svc)
        idle_connections = probe.connections()  # the API's
        before, counted_from = probe.commits(), probe.queries - 1  # that read commits after
        started = time.monotonic()
        names = svc.workers(cores, "run")
        ready_s = time.monotonic() - started
        samples = drain(probe, sum(len(v) for v in snaps.values()))
        own = probe.queries - counted_from  # the probe's transactions in the count
        time.sleep(11)  # PostgreSQL publishes an idle backend's counts within 10 s
        service_commits = probe.commits() - before - own
        probe.close()
        jobs = _sql(
            svc.db_url,
            "SELECT id, kind, state, worker, attempts, started_at, finished_at FROM jobs "
            "WHERE kind <> 'object' ORDER BY started_at",
        )
        result = summarise(config, jobs, samples, len(names))
        result.update(
            workers_ready_s=round(ready_s, 1),
            # committed transactions of the workers and the API while the queue drained
            db_transactions_per_job=round(service_commits / len(jobs), 1),
            db_connections_api=idle_connections,
            db_connections_per_worker_max=round(
                (result["db_connections_max"] - idle_connections) / len(names), 1
            ),
            bytes=bucket_bytes(svc, snaps),
            correctness=correctness(client, scenes, snaps),
        )
        return result


def summarise(
    config: str, jobs: list[dict[str, Any]], samples: dict[str, Any], n_workers: int
) -> dict[str, Any]:
    first = min(j["started_at"] for j in jobs)
    last = max(j["finished_at"] for j in jobs)
    wall = (last - first).total_seconds()
    snapshots = [j for j in jobs if j["kind"] == "snapshot"]
    per_job = [
        {
            "kind": j["kind"],
            "state": j["state"],
            "worker": j["worker"],
            "attempts": j["attempts"],
            "seconds": round((j["finished_at"] - j["started_at"]).total_seconds(), 1),
            "stages_s": stage_seconds(samples["stages"].get(j["id"], [])),
        }
        for j in jobs
    ]
    totals: dict[str, float] = defaultdict(float)
    for job in per_job:
        for stage, seconds in job["stages_s"].items():
            totals[f"{job['kind']}.{stage}"] += seconds
    return {
        "config": config,
        "workers": n_workers,
        "jobs": len(jobs),
        "snapshots": len(snapshots),
        "all_succeeded": all(j["state"] == "succeeded" for j in jobs),
        "drain_wall_s": round(wall, 1),
        "jobs_per_min": round(len(jobs) / wall * 60, 2),
        "snapshots_per_min": round(len(snapshots) / wall * 60, 2),
        "job_seconds_total": round(sum(p["seconds"] for p in per_job), 1),
        "stage_seconds_total": {k: round(v, 1) for k, v in sorted(totals.items())},
        "db_connections_max": max(samples["connections"]),
        "per_job": per_job,
    }


def storage_transfer(scenes: dict[str, Path]) -> dict[str, Any]:
    """One snapshot job's storage traffic timed alone: a capture put in the bucket, then
    fetched into an empty scratch cache (what a worker does before reconstructing) and a
    cloud of the run's size moved in (what it does after), with the workers' storage class."""
    from app.core.settings import Settings
    from app.core.storage import open_storage

    root = TMP / "storage-transfer"
    shutil.rmtree(root, ignore_errors=True)
    root.mkdir(parents=True)
    with services(root) as svc:
        os.environ.update(TEST_CREDENTIALS)
        settings = Settings(
            data_dir=root / "data",
            scratch_dir=root / "scratch",
            storage_url=f"s3://{svc.bucket}/twindelta",
            s3_endpoint_url=svc.s3_endpoint,
        )
        storage = open_storage(settings)
        capture = scenes["A"] / "before"
        files = sorted(p for p in capture.rglob("*") if p.is_file())
        size = sum(p.stat().st_size for p in files)
        t0 = time.perf_counter()
        for path in files:
            with path.open("rb") as fh:
                storage.write_stream(f"snap/{path.relative_to(capture).as_posix()}", fh)
        put_s = time.perf_counter() - t0
        shutil.rmtree(root / "scratch" / "cache", ignore_errors=True)
        t0 = time.perf_counter()
        storage.local_dir("snap/images")
        storage.local_dir("snap/labels")
        get_s = time.perf_counter() - t0
        cloud = root / "scratch" / "local" / "cloud.ply"
        cloud.parent.mkdir(parents=True, exist_ok=True)
        cloud.write_bytes(os.urandom(6 * 1024 * 1024))
        t0 = time.perf_counter()
        storage.move_in(cloud, "snap/reconstruction/cloud.ply")
        cloud_s = time.perf_counter() - t0
    return {
        "capture_bytes": size,
        "capture_files": len(files),
        "capture_put_s": round(put_s, 3),
        "capture_fetch_s": round(get_s, 3),
        "cloud_bytes": 6 * 1024 * 1024,
        "cloud_move_in_s": round(cloud_s, 3),
        "note": "moto's emulator on loopback: a lower bound on transfer time, not a real bucket",
    }


def report(results: dict[str, list[dict[str, Any]]], extra: dict[str, Any]) -> dict[str, Any]:
    """The result file's body from the runs done so far (medians over them)."""
    median = {c: statistics.median(r["drain_wall_s"] for r in rs) for c, rs in results.items()}
    ratio = median["1 worker"] / median["2 workers"]
    return {
        "what": "6 snapshots over 3 environments (+3 automatic comparisons), real pipeline",
        "scene": {"views": VIEWS, "width": WIDTH, "height": HEIGHT, "presets": "default"},
        "runs": min(len(rs) for rs in results.values()),
        "median_drain_wall_s": median,
        "median_jobs_per_min": {
            c: statistics.median(r["jobs_per_min"] for r in rs) for c, rs in results.items()
        },
        "throughput_ratio_2_to_1": round(ratio, 2),
        "ratio_per_run": [
            round(one["drain_wall_s"] / two["drain_wall_s"], 2)
            for one, two in zip(results["1 worker"], results["2 workers"], strict=False)
        ],
        "target_ratio": 1.8,
        "meets_target": ratio >= 1.8,
        **extra,
        "load_average_now": os.getloadavg(),
        "cpus": os.cpu_count(),
        "results": results,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help="one run of each configuration")
    parser.add_argument("--out", default=str(REPO_ROOT / "bench" / "results" / "workers.json"))
    args = parser.parse_args(argv)
    runs = 1 if args.quick else args.runs
    if shutil.which("taskset") is None or shutil.which("redis-server") is None:
        print("workers bench needs taskset and redis-server")
        return 1
    TMP.mkdir(parents=True, exist_ok=True)
    scenes = worlds()
    extra = {"load_average_before": os.getloadavg(), "storage_transfer": storage_transfer(scenes)}
    results: dict[str, list[dict[str, Any]]] = {c: [] for c in CONFIGS}
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    for run in range(runs):
        for config, cores in CONFIGS.items():
            result = one_run(config, cores, scenes, run)
            results[config].append(result)
            print(config, run, result["drain_wall_s"], "s", result["correctness"], flush=True)
        # written after every pair of runs, so a stopped bench keeps what it measured
        out.write_text(json.dumps(report(results, extra), indent=1, default=str))
    body = json.loads(out.read_text())
    print(json.dumps({k: body[k] for k in ("median_drain_wall_s", "throughput_ratio_2_to_1")}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
