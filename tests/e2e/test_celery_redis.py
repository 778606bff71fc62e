"""Production setup (PostgreSQL + Redis + Celery workers): a worker killed mid-job, a Redis
restart with jobs queued and a Redis restart mid-job lose nothing, each job finishes exactly
once, and a result finished before the fault comes out of it untouched."""

from __future__ import annotations

import io
import re
from collections.abc import Callable
from pathlib import Path

import httpx
import open3d as o3d
import pytest
from sqlalchemy import create_engine, text

from tests.e2e.conftest import (
    Processes,
    RedisServer,
    api_client,
    free_port,
    poll_job,
)

pytestmark = [pytest.mark.slow, pytest.mark.e2e, pytest.mark.postgres, pytest.mark.redis]


def mesh_bytes(tmp_path: Path, mesh: o3d.geometry.TriangleMesh, name: str) -> bytes:
    path = tmp_path / f"{name}.ply"
    o3d.io.write_triangle_mesh(str(path), mesh)
    return path.read_bytes()


def upload_object(client, name: str, data: bytes) -> dict[str, object]:  # type: ignore[no-untyped-def]
    r = client.post(
        "/v1/objects", files={"file": (f"{name}.ply", io.BytesIO(data))}, data={"name": name}
    )
    assert r.status_code == 202, r.text
    body: dict[str, object] = r.json()
    return body


def job_counts(client: httpx.Client) -> dict[tuple[str, str], float]:
    """Jobs by (kind, state), from /metrics."""
    found = re.findall(
        r'^twindelta_jobs\{kind="(\w+)",state="(\w+)"\} ([0-9.e+]+)$',
        client.get("/metrics").text,
        flags=re.MULTILINE,
    )
    return {(kind, state): float(n) for kind, state, n in found}


def rows(url: str, sql: str) -> list[tuple[object, ...]]:
    engine = create_engine(url)
    try:
        with engine.connect() as conn:
            return [tuple(r) for r in conn.execute(text(sql))]
    finally:
        engine.dispose()


def test_killed_worker_job_finishes_exactly_once(
    tmp_path: Path,
    pg_url: str,
    redis_server: RedisServer,
    processes: Callable[..., Processes],
) -> None:
    procs = processes(database_url=pg_url, broker_url=redis_server.url)
    port = free_port()
    procs.api(port)
    procs.worker("cpu1", "cpu")
    procs.worker("beat", "maintenance", "-B", "-s", str(tmp_path / "beat-schedule"))
    client = api_client(port)
    # a result finished before the fault: it must come out of it untouched
    box = o3d.geometry.TriangleMesh.create_box(0.3, 0.2, 0.1)
    earlier = upload_object(client, "box", mesh_bytes(tmp_path, box, "box"))
    assert poll_job(client, earlier["job"]["id"], 60)["state"] == "succeeded"  # type: ignore[index]
    earlier_body = client.get(f"/v1/objects/{earlier['id']}").json()
    torus = o3d.geometry.TriangleMesh.create_torus(0.2, 0.05, 200, 100)
    obj = upload_object(client, "torus", mesh_bytes(tmp_path, torus, "torus"))
    job_id = obj["job"]["id"]  # type: ignore[index]

    poll_job(client, job_id, 60, until=lambda j: j["state"] == "running")
    procs.kill("cpu1")  # SIGKILL mid-job: no ack, no heartbeat, no clean-up
    assert client.get(f"/v1/jobs/{job_id}").json()["state"] == "running"
    procs.worker("cpu2", "cpu")

    job = poll_job(client, job_id, 90)
    assert job["state"] == "succeeded", job
    assert job["attempts"] == 2  # the sweeper re-queued it once after the heartbeat stopped
    got = client.get(f"/v1/objects/{obj['id']}").json()
    assert got["state"] == "ready"
    assert got["diameter_m"] == pytest.approx(0.5, abs=0.01)
    assert got["symmetry"]["kind"] == "continuous"
    assert client.get(f"/v1/objects/{earlier['id']}").json() == earlier_body
    # nothing lost, nothing doubled: two jobs, both succeeded, no job.failed
    assert job_counts(client) == {("object", "succeeded"): 2.0}
    assert rows(pg_url, "SELECT type FROM events") == []


def test_redis_restart_with_queued_jobs_loses_none(
    tmp_path: Path,
    pg_url: str,
    redis_server: RedisServer,
    processes: Callable[..., Processes],
) -> None:
    procs = processes(database_url=pg_url, broker_url=redis_server.url)
    port = free_port()
    procs.api(port)
    client = api_client(port)
    box = o3d.geometry.TriangleMesh.create_box(0.3, 0.2, 0.1)
    data = mesh_bytes(tmp_path, box, "box")
    jobs = [upload_object(client, f"box{i}", data)["job"]["id"] for i in range(3)]  # type: ignore[index]
    for job_id in jobs:
        assert client.get(f"/v1/jobs/{job_id}").json()["state"] == "queued"

    redis_server.restart()  # an in-memory Redis: every queued message is gone

    procs.worker("cpu", "cpu")
    procs.worker("beat", "maintenance", "-B", "-s", str(tmp_path / "beat-schedule"))
    for job_id in jobs:
        job = poll_job(client, job_id, 90)
        assert job["state"] == "succeeded", job
        assert job["attempts"] == 1
        prepared = client.get(job["links"]["object"]).json()  # type: ignore[index]
        assert prepared["state"] == "ready" and prepared["diameter_m"] > 0.3
    assert job_counts(client) == {("object", "succeeded"): 3.0}
    # each message was lost with Redis and sent again by the sweeper
    assert all(sends >= 2 for (sends,) in rows(pg_url, "SELECT sends FROM jobs"))
    assert rows(pg_url, "SELECT type FROM events") == []


def test_redis_restart_mid_job_finishes_once(
    tmp_path: Path,
    pg_url: str,
    redis_server: RedisServer,
    processes: Callable[..., Processes],
) -> None:
    """Redis restarted while a job runs: the running job's unacknowledged message is gone
    with it; the job finishes on its worker, once, and jobs sent afterwards run too."""
    procs = processes(database_url=pg_url, broker_url=redis_server.url, test_slow_stage_s="6")
    port = free_port()
    procs.api(port)
    procs.worker("cpu", "cpu", "--include", "tests.e2e.slow_jobs")
    procs.worker("beat", "maintenance", "-B", "-s", str(tmp_path / "beat-schedule"))
    client = api_client(port)
    torus = o3d.geometry.TriangleMesh.create_torus(0.2, 0.05, 200, 100)
    obj = upload_object(client, "torus", mesh_bytes(tmp_path, torus, "torus"))
    job_id = obj["job"]["id"]  # type: ignore[index]
    poll_job(client, job_id, 60, until=lambda j: j["stage"] == "warmup")

    redis_server.restart()

    assert client.get(f"/v1/jobs/{job_id}").json()["state"] == "running"  # mid-job indeed
    job = poll_job(client, job_id, 90)
    assert job["state"] == "succeeded", job
    assert job["attempts"] == 1
    assert client.get(f"/v1/objects/{obj['id']}").json()["state"] == "ready"
    box = o3d.geometry.TriangleMesh.create_box(0.3, 0.2, 0.1)
    after = upload_object(client, "box", mesh_bytes(tmp_path, box, "box"))
    assert poll_job(client, after["job"]["id"], 90)["state"] == "succeeded"  # type: ignore[index]
    assert job_counts(client) == {("object", "succeeded"): 2.0}
    assert rows(pg_url, "SELECT type FROM events") == []
