"""Laser scans through the running service (uvicorn, a Celery worker, PostgreSQL, a private
Redis): a LAS scan is an environment's first snapshot, a photo snapshot after it is compared
with it automatically (``before`` is the scan); a scan whose markers cannot be found fails
its job and snapshot with NoUsableFrame and leaves the earlier snapshots alone. And a
300 MB scan upload streams: the API's peak memory grows by far less than the file.

The photo side runs the fast fake pipeline (:mod:`tests.e2e.fake_pipeline_plugin`); the scan
side is the production code."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from tests.e2e.conftest import (
    Processes,
    RedisServer,
    api_client,
    fake_pipeline_service,
    free_port,
    poll_job,
    wait_until,
)
from tests.e2e.test_twin_order import upload
from tests.workers.pipeline.scan_scene import cloud, write_las

pytestmark = [pytest.mark.slow, pytest.mark.e2e, pytest.mark.postgres, pytest.mark.redis]

CLASSES = ["drill", "bowl", "mug"]
SHEET = {"markers": {"size": 0.15, "poses": {"0": np.eye(4).tolist()}}}
ENV_FROM_SCAN = [[0.0, -1.0, 0.0, 2.0], [1.0, 0.0, 0.0, -1.0], [0.0, 0.0, 1.0, 0.5], [0, 0, 0, 1]]


def scan_file(tmp_path: Path, n: int = 5000) -> bytes:
    points, colors = cloud(n, seed=7)
    path = tmp_path / "site.las"
    write_las(path, points, colors)
    return path.read_bytes()


def test_a_scan_is_the_baseline_a_photo_snapshot_is_compared_with(
    tmp_path: Path,
    pg_url: str,
    redis_server: RedisServer,
    processes: Callable[..., Processes],
) -> None:
    procs = processes(database_url=pg_url, broker_url=redis_server.url)
    client = fake_pipeline_service(procs)
    r = client.post(
        "/v1/environments", json={"name": "plant", "classes": CLASSES, "reference": SHEET}
    )
    assert r.status_code == 201, r.text
    env_id = r.json()["id"]

    # 1. the scan: the first snapshot
    body = scan_file(tmp_path)
    r = client.post(
        f"/v1/environments/{env_id}/scans",
        files={"file": ("site.las", body, "application/octet-stream")},
        data={"frame": json.dumps({"transform": ENV_FROM_SCAN})},
    )
    assert r.status_code == 202, r.text
    scan_id = r.json()["snapshot"]["id"]
    job = poll_job(client, r.json()["job"]["id"], 120)
    assert job["state"] == "succeeded", job
    scan = client.get(f"/v1/snapshots/{scan_id}").json()
    assert scan["source"] == "scan" and scan["state"] == "reconstructed"
    assert scan["quality"]["frame_method"] == "transform" and scan["quality"]["points_in"] == 5000
    assert scan["twin_update"] == "baseline" and scan["comparison"] is None
    cloud_bytes = client.get(f"/v1/snapshots/{scan_id}/pointcloud").content
    path = tmp_path / "scan_cloud.ply"
    path.write_bytes(cloud_bytes)
    got = np.asarray(o3d.io.read_point_cloud(str(path)).points)
    assert len(got) == scan["quality"]["points"] > 0
    points, _ = cloud(5000, seed=7)
    moved = points @ np.asarray(ENV_FROM_SCAN)[:3, :3].T + np.asarray(ENV_FROM_SCAN)[:3, 3]
    np.testing.assert_allclose(got.min(axis=0), moved.min(axis=0), atol=0.003)
    np.testing.assert_allclose(got.max(axis=0), moved.max(axis=0), atol=0.003)

    # 2. a photo snapshot: reconstructed (fake), then compared with the scan
    photo_id = upload(client, env_id, {"drill": 0.2, "bowl": 0.5}, "p")
    wait_until(
        lambda: client.get(f"/v1/snapshots/{photo_id}").json()["comparison"] is not None,
        60,
        "the automatic comparison",
    )
    photo = client.get(f"/v1/snapshots/{photo_id}").json()
    assert photo["source"] == "photos" and photo["state"] == "reconstructed"
    comparison = client.get(f"/v1/comparisons/{photo['comparison']}").json()
    assert (comparison["before"], comparison["after"]) == (scan_id, photo_id)
    assert poll_job(client, comparison["job"], 60)["state"] == "succeeded"
    comparison = client.get(f"/v1/comparisons/{photo['comparison']}").json()
    assert comparison["applied_to_twin"] is True
    assert sorted((c["type"], c["object"]) for c in comparison["changes"]) == [
        ("added", "bowl"),
        ("added", "drill"),
    ]
    state = client.get(f"/v1/environments/{env_id}/state").json()
    assert sorted(o["object"] for o in state["objects"]) == ["bowl", "drill"]
    assert state["twin"]["snapshot"] == photo_id

    # 3. a scan whose marker sheet is not in it: the job and snapshot fail, nothing else
    r = client.post(
        f"/v1/environments/{env_id}/scans",
        files={"file": ("nosheet.las", scan_file(tmp_path, 2000), "application/octet-stream")},
        data={"frame": json.dumps({"markers": True})},
    )
    assert r.status_code == 202, r.text
    job = poll_job(client, r.json()["job"]["id"], 120)
    assert job["state"] == "failed" and job["error"]["code"] == "NoUsableFrame", job
    assert "markers" in job["error"]["detail"]
    failed = client.get(f"/v1/snapshots/{r.json()['snapshot']['id']}").json()
    assert failed["state"] == "failed" and failed["source"] == "scan"
    for snap_id in (scan_id, photo_id):
        assert client.get(f"/v1/snapshots/{snap_id}").json()["state"] == "reconstructed"
    assert client.get(f"/v1/snapshots/{scan_id}/pointcloud").content == cloud_bytes
    wait_until(
        lambda: client.get(f"/v1/snapshots/{failed['id']}").json()["twin_update"] == "skipped",
        30,
        "the twin to skip the failed scan",
    )
    state = client.get(f"/v1/environments/{env_id}/state").json()
    assert sorted(o["object"] for o in state["objects"]) == ["bowl", "drill"]


def peak_rss_bytes(pid: int) -> int:
    """The process's peak resident set size (VmHWM), bytes."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) * 1024
    raise AssertionError("no VmHWM in /proc")


def test_a_300_mb_scan_streams_through_the_api(
    tmp_path: Path,
    pg_url: str,
    redis_server: RedisServer,
    processes: Callable[..., Processes],
) -> None:
    """The API alone (no worker: the job stays queued). The peak RSS of the API process
    grows by less than a third of the file while it takes a 300 MB PLY (the body is spooled
    to disk by the multipart parser and copied into storage in 1 MiB chunks; measured: no
    growth). Reading the file whole would add 300 MB."""
    procs = processes(database_url=pg_url, broker_url=redis_server.url)
    port = free_port()
    procs.api(port)
    client = api_client(port)
    pid = procs.procs["api"].pid
    env_id = client.post("/v1/environments", json={"name": "big", "classes": CLASSES}).json()["id"]
    frame = {"frame": json.dumps({"transform": np.eye(4).tolist()})}
    small = client.post(  # warms up the route (imports, first request)
        f"/v1/environments/{env_id}/scans",
        files={"file": ("small.las", scan_file(tmp_path), "application/octet-stream")},
        data=frame,
    )
    assert small.status_code == 202, small.text
    n = 25_000_000  # × 12 bytes: 300 MB
    header = (
        f"ply\nformat binary_little_endian 1.0\nelement vertex {n}\nproperty float x\n"
        "property float y\nproperty float z\nend_header\n"
    ).encode()
    big = tmp_path / "big.ply"
    with big.open("wb") as fh:
        fh.write(header)
        block = np.random.default_rng(0).random((1_000_000, 3), np.float32).tobytes()
        for _ in range(n // 1_000_000):
            fh.write(block)
    size = big.stat().st_size
    before = peak_rss_bytes(pid)
    with big.open("rb") as fh:
        r = client.post(
            f"/v1/environments/{env_id}/scans",
            files={"file": ("big.ply", fh, "application/octet-stream")},
            data=frame,
            timeout=300,
        )
    assert r.status_code == 202, r.text
    growth = peak_rss_bytes(pid) - before
    print(
        f"API peak RSS {before / 1e6:.0f} MB, +{growth / 1e6:.0f} MB for a {size / 1e6:.0f} MB scan"
    )
    assert growth < size / 3
    snap = r.json()["snapshot"]
    assert snap["upload_bytes"] == size
    stored = tmp_path / "data" / "files" / "snapshots" / snap["id"] / "scan" / "scan.ply"
    assert stored.stat().st_size == size
    with stored.open("rb") as fh, big.open("rb") as want:
        assert fh.read(1 << 20) == want.read(1 << 20)
