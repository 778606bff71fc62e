"""Production setup (PostgreSQL + Redis + Celery workers): a worker killed mid-job and a
Redis restart with jobs queued lose nothing, and each job finishes exactly once."""

from __future__ import annotations

import io
from collections.abc import Callable
from pathlib import Path

import open3d as o3d
import pytest

from tests.e2e.conftest import (
    Processes,
    RedisServer,
    api_client,
    free_port,
    poll_job,
)

pytestmark = [pytest.mark.e2e, pytest.mark.postgres, pytest.mark.redis]


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
    metrics = client.get("/metrics").text
    assert 'twindelta_jobs{kind="object",state="succeeded"} 1.0' in metrics


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
