"""The API with S3 storage (a bucket on the loopback emulator, bench/loopback.py): a
snapshot archive uploaded over HTTP lands in the bucket, not in the local folder; photos and
clouds stream back byte-identical; derived files (LAZ, decimated) are published to the
bucket; deleting its environment empties the snapshot's prefix; a resumable upload is staged
in this host's scratch; jobs run with another scratch (another host) read and publish
through the bucket; /readyz probes the bucket."""

from __future__ import annotations

import hashlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from sqlalchemy.orm import Session, sessionmaker

from app.core import ingest, snapshots
from app.core.enums import JobState, SnapshotState
from app.core.models import Job
from app.core.settings import get_settings
from app.core.storage import S3Storage, open_storage
from app.main import create_app
from bench import loopback as s3_server
from tests.app.api.test_console_api import write_ply
from tests.app.api.test_snapshots_upload import (
    CLASSES,
    archive_part,
    capture,
    make_env,
    nested,
    upload,
    zip_bytes,
)
from tests.app.api.test_uploads_api import create as create_upload
from tests.app.api.test_uploads_api import patch as patch_upload
from tests.app.conftest import Keys, SentTasks
from tests.app.core import test_twin_order as twin_order
from tests.workers import fake_pipeline
from workers import snapshot as snapshot_glue


@dataclass
class Bucket:
    endpoint: str
    name: str
    prefix: str

    def listed(self, under: str = "") -> list[str]:
        start = f"{self.prefix}/{under}"
        return [
            k[len(self.prefix) + 1 :]
            for k in s3_server.object_keys(self.endpoint, self.name)
            if k.startswith(start)
        ]


@pytest.fixture
def bucket(
    s3_storage_url: tuple[str, str], data_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> Bucket:
    """The test's settings switched to S3 storage (scratch in the test's data folder)."""
    url, endpoint = s3_storage_url
    monkeypatch.setenv("TWINDELTA_STORAGE_URL", url)
    monkeypatch.setenv("TWINDELTA_S3_ENDPOINT_URL", endpoint)
    get_settings.cache_clear()
    name, _, prefix = url.removeprefix("s3://").partition("/")
    return Bucket(endpoint, name, prefix)


@pytest.fixture
def s3_client(
    bucket: Bucket, session_factory: sessionmaker[Session], sent_tasks: SentTasks
) -> Iterator[TestClient]:
    with TestClient(create_app()) as c:
        yield c


def _local_snapshot_files(data_dir: Path) -> list[Path]:
    files = data_dir / "files"
    return [p for p in files.rglob("*") if p.is_file()] if files.exists() else []


def test_a_snapshot_lives_in_the_bucket_and_streams_back(
    s3_client: TestClient,
    keys: Keys,
    bucket: Bucket,
    data_dir: Path,
    session_factory: sessionmaker[Session],
) -> None:
    client = s3_client
    assert client.get("/readyz").json()["checks"]["storage"] == "ok"
    env_id = make_env(client, keys)
    files = capture()
    r = upload(client, keys, env_id, archive_part("cap.zip", zip_bytes(nested(files))))
    assert r.status_code == 202, r.text
    snap_id, job_id = r.json()["snapshot"]["id"], r.json()["job"]["id"]
    assert sorted(bucket.listed(f"snapshots/{snap_id}/")) == sorted(
        [f"snapshots/{snap_id}/images/{n}" for n in ("a0.jpg", "a1.jpg", "a2.png")]
        + [f"snapshots/{snap_id}/labels/{n}" for n in ("a0.txt", "a1.txt")]
        + [f"snapshots/{snap_id}/cameras.json"]
    )
    assert _local_snapshot_files(data_dir) == []  # the local folder holds no snapshot file

    # the worker's ingest stage, on a fresh scratch (another host): reads through the cache
    settings = get_settings()
    worker = open_storage(settings.model_copy(update={"scratch_dir": data_dir / "worker"}))
    assert isinstance(worker, S3Storage)
    with session_factory.begin() as s:
        prefix = snapshots.get(s, snap_id).storage_prefix
        records = ingest.read_capture(worker, prefix, CLASSES, settings)
        ingest.record_images(s, snap_id, records)
    assert [r.name for r in records] == ["a0.jpg", "a1.jpg", "a2.png"]
    assert records[0].detections and records[2].labels_key is None

    for name in ("a0.jpg", "a2.png"):
        r = client.get(f"/v1/snapshots/{snap_id}/images/{name}", headers=keys.headers("read"))
        assert r.status_code == 200, r.text
        assert r.content == files[name]
    assert r.headers["content-type"] == "image/png"

    # a reconstructed cloud, as the worker publishes it
    staged = worker.tmp_dir() / "cloud.ply"
    rng = np.random.default_rng(0)
    points = rng.uniform(-1, 1, (5000, 3))
    write_ply(staged, points, rng.integers(0, 255, (5000, 3), dtype=np.uint8))
    ply = staged.read_bytes()
    cloud_key = f"{prefix}/reconstruction/cloud.ply"
    worker.move_in(staged, cloud_key)
    with session_factory.begin() as s:
        snap = snapshots.get(s, snap_id)
        snap.state, snap.pointcloud_key = SnapshotState.reconstructed, cloud_key
        s.get_one(Job, job_id).state = JobState.succeeded

    read = keys.headers("read")
    r = client.get(f"/v1/snapshots/{snap_id}/pointcloud", headers=read)
    assert (
        r.status_code == 200 and hashlib.sha256(r.content).digest() == hashlib.sha256(ply).digest()
    )
    r = client.get(f"/v1/snapshots/{snap_id}/pointcloud?format=laz", headers=read)
    assert r.status_code == 200 and r.content[:4] == b"LASF"
    r = client.get(f"/v1/snapshots/{snap_id}/pointcloud?max_points=1000", headers=read)
    assert r.status_code == 200 and r.headers["x-total-points"] == "5000"
    assert f"snapshots/{snap_id}/reconstruction/cloud.laz" in bucket.listed()
    assert f"snapshots/{snap_id}/reconstruction/decimated/1000.ply" in bucket.listed()
    assert _local_snapshot_files(data_dir) == []

    r = client.delete(f"/v1/environments/{env_id}", headers=keys.headers("admin"))
    assert r.status_code == 204, r.text
    assert bucket.listed(f"snapshots/{snap_id}/") == []
    assert not (data_dir / "scratch" / "cache" / "snapshots" / snap_id).exists()


def test_a_resumable_upload_is_staged_on_this_host_and_lands_in_the_bucket(
    s3_client: TestClient, keys: Keys, bucket: Bucket, data_dir: Path
) -> None:
    client = s3_client
    env_id = make_env(client, keys)
    body = zip_bytes(nested(capture()))
    r = create_upload(client, keys, env_id, body)
    assert r.status_code == 201, r.text
    url = r.headers["Location"]
    partial = data_dir / "scratch" / "local" / "uploads" / url.rsplit("/", 1)[1]
    half = len(body) // 2
    assert patch_upload(client, keys, url, 0, body[:half]).status_code == 204
    assert partial.stat().st_size == half and bucket.listed("uploads/") == []
    r = patch_upload(client, keys, url, half, body[half:])
    assert r.status_code == 204, r.text
    snap_id = r.headers["Twindelta-Snapshot"]
    assert len(bucket.listed(f"snapshots/{snap_id}/images/")) == 3
    assert not partial.exists() and _local_snapshot_files(data_dir) == []


def test_readyz_names_a_missing_bucket(
    bucket: Bucket, data_dir: Path, monkeypatch: pytest.MonkeyPatch, s3_client: TestClient
) -> None:
    monkeypatch.setenv("TWINDELTA_STORAGE_URL", "s3://twindelta-no-such-bucket")
    get_settings.cache_clear()
    r = s3_client.get("/readyz")
    assert r.status_code == 503
    assert r.json()["checks"]["storage"] == (
        "error: bucket twindelta-no-such-bucket: no such bucket"
    )


def test_jobs_on_another_host_read_and_publish_through_the_bucket(
    s3_client: TestClient,
    keys: Keys,
    bucket: Bucket,
    data_dir: Path,
    session_factory: sessionmaker[Session],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Snapshot and comparison jobs (production glue, the fake pipeline for geometry) on a
    "worker host" whose scratch is its own: they read the captures from the bucket and
    publish clouds, cameras and change clusters to it; the API host then serves them."""
    fake_pipeline.install(monkeypatch.setattr)
    client = s3_client
    env_id = twin_order.make_env(client, keys)
    snaps = [twin_order.upload(client, keys, env_id, scene) for scene in twin_order.SCENES[:2]]
    monkeypatch.setenv("TWINDELTA_SCRATCH_DIR", str(data_dir / "worker"))
    get_settings.cache_clear()
    for snap_id in snaps:
        job_id = twin_order.snapshot_job(session_factory, snap_id)
        assert snapshot_glue.run(job_id) == "succeeded"
    assert twin_order.run_comparisons_newest_first(session_factory) == [2]
    monkeypatch.delenv("TWINDELTA_SCRATCH_DIR")
    get_settings.cache_clear()

    for snap_id in snaps:
        assert set(bucket.listed(f"snapshots/{snap_id}/reconstruction/")) == {
            f"snapshots/{snap_id}/reconstruction/cloud.ply",
            f"snapshots/{snap_id}/reconstruction/cameras.json",
        }
    [clusters] = bucket.listed(f"snapshots/{snaps[1]}/comparisons/")
    assert clusters.endswith("/clusters.npz")
    comparison_id = clusters.split("/")[3]
    r = client.get(f"/v1/comparisons/{comparison_id}/clusters", headers=keys.headers("read"))
    assert r.status_code == 200, r.text
    assert (data_dir / "scratch" / "cache" / clusters).is_file()  # fetched by the API host
    assert not (data_dir / "worker" / "local" / ".work").exists() or not any(
        (data_dir / "worker" / "local" / ".work").iterdir()
    )  # work folders removed after each job
    assert _local_snapshot_files(data_dir) == []
