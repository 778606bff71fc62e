"""Jobs and exports against S3 storage (a bucket on the loopback emulator): the snapshot job
lists the photos in the bucket once; a stale attempt on one worker host that publishes after
the winner on another committed removes its own files and leaves the winner's; counting a
cloud's points reads its header only, so a host that serves a decimated cloud made
elsewhere fetches nothing whole."""

from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from sqlalchemy.orm import Session, sessionmaker

from app.core import jobs
from app.core.enums import JobState
from app.core.export import decimate
from app.core.models import Job, Snapshot
from app.core.settings import get_settings
from app.core.storage import S3Storage, open_storage
from tests.app.api import test_s3_storage as s3_api
from tests.app.api.test_s3_storage import Bucket
from tests.app.conftest import Keys
from tests.app.core import test_twin_order as twin_order
from tests.workers import fake_pipeline
from workers import snapshot as snapshot_glue
from workers.runner import JobContext, Published
from workers.runner import publish as real_publish

bucket, s3_client = s3_api.bucket, s3_api.s3_client  # the fixtures: S3 settings, the API


@pytest.fixture
def uploaded(
    s3_client: TestClient,
    keys: Keys,
    session_factory: sessionmaker[Session],
    monkeypatch: pytest.MonkeyPatch,
) -> tuple[str, str]:
    """(snapshot id, its job id) of a capture uploaded to the bucket; the fake pipeline."""
    fake_pipeline.install(monkeypatch.setattr)
    env_id = twin_order.make_env(s3_client, keys)
    snap_id = twin_order.upload(s3_client, keys, env_id, {"drill": 0.2})
    return snap_id, twin_order.snapshot_job(session_factory, snap_id)


def test_the_snapshot_job_lists_the_photos_once(
    uploaded: tuple[str, str], bucket: Bucket, data_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The photos are listed (ListObjectsV2) once a job: fetched, then read and reconstructed
    from the same local folder. Counted on the worker host's client (boto3's event hook)."""
    snap_id, job_id = uploaded
    monkeypatch.setenv("TWINDELTA_SCRATCH_DIR", str(data_dir / "worker"))
    get_settings.cache_clear()
    worker = open_storage(get_settings())  # the runner's own: one client per process
    assert isinstance(worker, S3Storage)
    listed: Counter[str] = Counter()

    def count(params: dict[str, Any], **_kwargs: Any) -> None:
        listed[params["Prefix"].removeprefix(f"{bucket.prefix}/snapshots/{snap_id}/")] += 1

    event = "before-parameter-build.s3.ListObjectsV2"
    worker.client.meta.events.register(event, count)
    try:
        assert snapshot_glue.run(job_id) == "succeeded"
    finally:
        worker.client.meta.events.unregister(event, count)
    # the photos, the labels, and the reconstruction folders next to the one published
    assert listed == {"images/": 1, "labels/": 1, "reconstruction/": 1}


def test_a_stale_attempt_publishing_after_the_winner_removes_its_own_files(
    uploaded: tuple[str, str],
    bucket: Bucket,
    data_dir: Path,
    session_factory: sessionmaker[Session],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Attempt 1 on host A is still uploading when its job is requeued (a heartbeat
    timeout) and attempt 2 runs it to the end on host B; attempt 1's files land after the
    winner committed, under its own folder, and go when it finds it lost the job."""
    snap_id, job_id = uploaded
    monkeypatch.setenv("TWINDELTA_HEARTBEAT_INTERVAL_S", "3600")

    def on_host(name: str) -> None:
        monkeypatch.setenv("TWINDELTA_SCRATCH_DIR", str(data_dir / name))
        get_settings.cache_clear()

    def publish(ctx: JobContext, root: str, files: Any) -> Published:
        if ctx.attempt == 1:  # the winner runs meanwhile on host B
            with session_factory.begin() as s:
                assert jobs.requeue(s, job_id, 1)
            on_host("b")
            assert snapshot_glue.run(job_id) == "succeeded"
            on_host("a")
        return real_publish(ctx, root, files)

    monkeypatch.setattr(snapshot_glue, "publish", publish)
    on_host("a")
    assert snapshot_glue.run(job_id) == "lost"
    with session_factory() as s:
        snap, job = s.get_one(Snapshot, snap_id), s.get_one(Job, job_id)
        assert (job.state, job.attempts) == (JobState.succeeded, 2)
        folder = f"snapshots/{snap_id}/reconstruction/{job_id}-2"
        assert (snap.pointcloud_key, snap.cameras_key) == (
            f"{folder}/cloud.ply",
            f"{folder}/cameras.json",
        )
    assert sorted(bucket.listed(f"snapshots/{snap_id}/reconstruction/")) == [
        f"{folder}/cameras.json",
        f"{folder}/cloud.ply",
    ]


class _Counted:
    """A stream read through, counting the bytes read."""

    def __init__(self, body: Any) -> None:
        self.body, self.read_bytes = body, 0

    def read(self, size: int = -1) -> bytes:
        data: bytes = self.body.read(size)
        self.read_bytes += len(data)
        return data

    def __enter__(self) -> _Counted:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.body.close()


def test_counting_a_clouds_points_reads_its_header_only(
    bucket: Bucket, data_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A 15 MB cloud decimated on a worker host; another host asked for the same level counts
    the points from the first 4 KiB of the object's stream and fetches nothing into its
    cache (the decimated file is fresh, so the cloud is not needed there)."""
    settings = get_settings()
    worker = open_storage(settings.model_copy(update={"scratch_dir": data_dir / "worker"}))
    api = open_storage(settings)
    assert isinstance(api, S3Storage) and isinstance(worker, S3Storage)
    n = 1_000_000
    records = np.zeros(n, decimate.RECORD)
    records["x"] = np.random.default_rng(0).random(n)
    key = "snapshots/s/reconstruction/j-1/cloud.ply"
    worker.write_bytes(key, decimate.ply_header(n) + records.tobytes())
    made = decimate.ensure_decimated(worker, key, 1000)
    assert (made.n_points, made.total_points) == (1000, n)

    opened: list[_Counted] = []
    real_open = api.open

    def counted_open(stored: str) -> _Counted:
        opened.append(_Counted(real_open(stored)))
        return opened[-1]

    monkeypatch.setattr(api, "open", counted_open)
    assert decimate.total_points(api, key) == n
    assert decimate.ensure_decimated(api, key, 1000) == made
    assert [o.read_bytes for o in opened] == [4096, 4096]
    assert not [p for p in api.cache.rglob("*") if p.is_file()]  # nothing fetched whole
