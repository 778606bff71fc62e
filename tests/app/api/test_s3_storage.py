"""The API with S3 storage (a bucket on the loopback emulator, bench/loopback.py): a
snapshot archive uploaded over HTTP lands in the bucket, not in the local folder; photos and
clouds stream back byte-identical; derived files (LAZ, decimated) are published to the
bucket; deleting its environment empties the snapshot's prefix; a resumable upload is stored
in parts in the bucket, so three API hosts (own scratch each) can take its requests in turn,
and two PATCHes at one offset on two hosts cannot both count; jobs run with another scratch
(another host) read and publish through the bucket; /readyz probes the bucket."""

from __future__ import annotations

import hashlib
from collections.abc import Iterator
from contextlib import ExitStack
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from sqlalchemy.orm import Session, sessionmaker

from app.core import ingest, snapshots, uploads
from app.core.enums import JobState, SnapshotState
from app.core.errors import Conflict
from app.core.models import Job, ResumableUpload, utcnow
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
from tests.app.api.test_uploads_api import new_upload
from tests.app.api.test_uploads_api import patch as patch_upload
from tests.app.conftest import Keys, SentTasks
from tests.app.core import test_twin_order as twin_order
from tests.app.core.test_uploads import spooled
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


def test_a_resumable_upload_is_stored_in_parts_and_lands_in_the_bucket(
    s3_client: TestClient, keys: Keys, bucket: Bucket, data_dir: Path
) -> None:
    client = s3_client
    env_id = make_env(client, keys)
    body = zip_bytes(nested(capture()))
    r = create_upload(client, keys, env_id, body)
    assert r.status_code == 201, r.text
    url = r.headers["Location"]
    upload_id = url.rsplit("/", 1)[1]
    half = len(body) // 2
    assert patch_upload(client, keys, url, 0, body[:half]).status_code == 204
    [part] = bucket.listed(f"uploads/{upload_id}/")
    assert part.startswith(f"uploads/{upload_id}/{0:020d}.")
    r = patch_upload(client, keys, url, half, body[half:])
    assert r.status_code == 204, r.text
    snap_id = r.headers["Twindelta-Snapshot"]
    assert len(bucket.listed(f"snapshots/{snap_id}/images/")) == 3
    assert bucket.listed("uploads/") == [] and _local_snapshot_files(data_dir) == []
    assert not (data_dir / "scratch" / "local" / "uploads" / upload_id).exists()


@dataclass
class Host:
    """One API host: its own app and scratch folder; the database and bucket are shared."""

    client: TestClient
    scratch: Path


@pytest.fixture
def hosts(
    bucket: Bucket,
    data_dir: Path,
    session_factory: sessionmaker[Session],
    sent_tasks: SentTasks,
) -> Iterator[list[Host]]:
    """Three API hosts (separate ``create_app`` instances, scratch ``host1..3``)."""
    settings = get_settings()
    with ExitStack() as stack:
        found = []
        for n in (1, 2, 3):
            scratch = data_dir / f"host{n}"
            own = settings.model_copy(update={"scratch_dir": scratch})
            app = create_app()
            app.dependency_overrides[get_settings] = lambda own=own: own
            found.append(Host(stack.enter_context(TestClient(app)), scratch))
        yield found


def _object(bucket: Bucket, key: str) -> bytes:
    body = s3_server.client(bucket.endpoint).get_object(
        Bucket=bucket.name, Key=f"{bucket.prefix}/{key}"
    )["Body"]
    return bytes(body.read())


def test_a_resumable_upload_created_patched_and_finished_on_three_hosts(
    hosts: list[Host], keys: Keys, bucket: Bucket
) -> None:
    """Created on host 1, PATCHed on host 2, finished on host 3: every host answers the
    offset from the database, a stale PATCH on host 1 is 409, and the snapshot's files land
    in the bucket byte for byte; no part is left in the bucket or any host's scratch."""
    one, two, three = (h.client for h in hosts)
    env_id = make_env(one, keys)
    files = capture()
    body = zip_bytes(nested(files))
    r = create_upload(one, keys, env_id, body)
    assert r.status_code == 201, r.text
    url = r.headers["Location"]
    upload_id = url.rsplit("/", 1)[1]
    third = len(body) // 3
    r = patch_upload(two, keys, url, 0, body[:third])
    assert r.status_code == 204 and r.headers["Upload-Offset"] == str(third), r.text
    for host in (one, two, three):
        r = host.head(url, headers={**keys.headers("capture"), "Tus-Resumable": "1.0.0"})
        assert r.headers["Upload-Offset"] == str(third)
    r = patch_upload(one, keys, url, 0, body[:third])
    assert r.status_code == 409 and r.json()["error"] == "OffsetMismatch"
    r = patch_upload(two, keys, url, third, body[third : 2 * third])
    assert r.status_code == 204, r.text
    assert len(bucket.listed(f"uploads/{upload_id}/")) == 2
    r = patch_upload(three, keys, url, 2 * third, body[2 * third :])
    assert r.status_code == 204, r.text
    snap_id = r.headers["Twindelta-Snapshot"]
    stored = {
        "images/a0.jpg": files["a0.jpg"],
        "images/a1.jpg": files["a1.jpg"],
        "images/a2.png": files["a2.png"],
        "labels/a0.txt": files["a0.txt"],
        "labels/a1.txt": files["a1.txt"],
        "cameras.json": files["cameras.json"],
    }
    assert sorted(bucket.listed(f"snapshots/{snap_id}/")) == sorted(
        f"snapshots/{snap_id}/{name}" for name in stored
    )
    for name, content in stored.items():
        assert _object(bucket, f"snapshots/{snap_id}/{name}") == content, name
    assert bucket.listed("uploads/") == []
    for each in hosts:
        left = each.scratch / "local" / "uploads"
        assert not left.exists() or [p for p in left.rglob("*") if p.is_file()] == []
    info = two.get(url, headers=keys.headers("capture")).json()
    assert (info["state"], info["snapshot"]) == ("completed", snap_id)


def test_two_hosts_patching_one_offset_the_second_stored_is_409(
    hosts: list[Host],
    keys: Keys,
    bucket: Bucket,
    session_factory: sessionmaker[Session],
) -> None:
    """Hosts 2 and 3 both take a PATCH at offset 0 and spool it; host 2 stores first and
    moves the offset, host 3's store is 409 OffsetMismatch and its part leaves the bucket.
    The upload then completes from host 2's offset with the right bytes."""
    body = zip_bytes(nested(capture()))
    url, row = new_upload(hosts[0].client, keys, session_factory, body)
    upload_id = row.id
    settings = get_settings()
    won, lost = (
        spooled(
            open_storage(settings.model_copy(update={"scratch_dir": host.scratch})), row, 0, chunk
        )
        for host, chunk in ((hosts[1], body[:100]), (hosts[2], b"\0" * 200))
    )
    assert won.store(session_factory, settings).offset_bytes == 100
    with pytest.raises(Conflict) as refused:
        lost.store(session_factory, settings)
    assert refused.value.code == "OffsetMismatch"
    assert bucket.listed(f"uploads/{upload_id}/") == [f"uploads/{upload_id}/{won.name}"]
    assert not lost.path.exists()
    r = patch_upload(hosts[2].client, keys, url, 100, body[100:])
    assert r.status_code == 204 and "Twindelta-Snapshot" in r.headers, r.text
    assert bucket.listed("uploads/") == []


def test_the_upload_sweep_empties_the_bucket_of_expired_and_orphaned_parts(
    s3_client: TestClient, keys: Keys, bucket: Bucket, session_factory: sessionmaker[Session]
) -> None:
    """maintenance.uploads with S3: an expired upload's parts leave the bucket with its row,
    a part folder with no row goes once old, a live upload's parts stay."""
    body = zip_bytes(nested(capture()))
    old_url, old = new_upload(s3_client, keys, session_factory, body)
    live_url = create_upload(s3_client, keys, old.environment_id, body).headers["Location"]
    for url in (old_url, live_url):
        assert patch_upload(s3_client, keys, url, 0, body[:100]).status_code == 204
    storage = open_storage(get_settings())
    storage.write_bytes(f"uploads/no-row/{0:020d}.0123456789abcdef", b"left by a deleted upload")
    with session_factory.begin() as s:
        row = s.get(ResumableUpload, old.id)
        assert row is not None
        row.expires_at = utcnow() - timedelta(seconds=1)
    with session_factory.begin() as s:
        counts = uploads.expire(s, storage, orphan_age_s=0, now=utcnow() + timedelta(seconds=2))
    assert counts == {"uploads_expired": 1, "uploads_orphaned": 1}
    [part] = bucket.listed("uploads/")
    assert part.startswith(f"uploads/{live_url.rsplit('/', 1)[1]}/")


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

    for snap_id in snaps:  # published under the attempt's folder
        job_id = twin_order.snapshot_job(session_factory, snap_id)
        folder = f"snapshots/{snap_id}/reconstruction/{job_id}-1"
        assert set(bucket.listed(f"snapshots/{snap_id}/reconstruction/")) == {
            f"{folder}/cloud.ply",
            f"{folder}/cameras.json",
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
