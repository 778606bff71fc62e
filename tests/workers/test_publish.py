"""Jobs publish their files before the persist transaction, under a folder of their attempt
(workers.runner.publish): the snapshot job's cloud and cameras, the object job's artefacts.
A stale attempt (its job requeued after a heartbeat timeout, another attempt ran it) never
touches what the winner recorded and leaves nothing behind; a persist that fails removes
what was published. Production glue, fake pipeline, local storage (PostgreSQL and SQLite)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import open3d as o3d
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from app.core import change_clusters, jobs
from app.core.enums import JobState, ObjectState
from app.core.models import Comparison, Job, LibraryObject, Snapshot
from app.core.settings import get_settings
from app.core.storage import LocalStorage
from tests.app.conftest import Keys, SentTasks
from tests.app.core.test_twin_order import (
    SCENES,
    make_env,
    queued_comparisons,
    snapshot_job,
    upload,
)
from tests.workers import fake_pipeline
from workers import comparison as comparison_glue
from workers import objects as object_glue
from workers import snapshot as snapshot_glue
from workers.runner import JobContext, run_job, unpublish


@pytest.fixture
def storage(data_dir: Path, monkeypatch: pytest.MonkeyPatch) -> LocalStorage:
    """The jobs' storage, with heartbeats far apart (a stale attempt never learns it lost
    before it tries to persist)."""
    monkeypatch.setenv("TWINDELTA_HEARTBEAT_INTERVAL_S", "3600")
    get_settings.cache_clear()
    fake_pipeline.install(monkeypatch.setattr)
    return LocalStorage(get_settings().resolved_storage_dir)


@pytest.fixture
def uploaded(
    client: TestClient,
    keys: Keys,
    session_factory: sessionmaker[Session],
    sent_tasks: SentTasks,
    storage: LocalStorage,
) -> tuple[str, str]:
    """(snapshot id, its job id) of one uploaded capture."""
    snap_id = upload(client, keys, make_env(client, keys), {"drill": 0.2})
    return snap_id, snapshot_job(session_factory, snap_id)


def row(factory: sessionmaker[Session], model: Any, key: str) -> Any:
    with factory() as s:
        found = s.get(model, key)
        assert found is not None
        s.expunge(found)
        return found


def published_folders(storage: LocalStorage, root: str) -> list[str]:
    return sorted(storage.folders(root))


@pytest.fixture
def transfers(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """The keys moved in, and ``finish`` where a job's final transaction began (jobs.finish
    is its first statement), in order."""
    log: list[str] = []
    real_move_in, real_finish = LocalStorage.move_in, jobs.finish

    def move_in(self: LocalStorage, local: Path, key: str) -> None:
        log.append(key)
        real_move_in(self, local, key)

    def finish(*args: Any, **kwargs: Any) -> Any:
        log.append("finish")
        return real_finish(*args, **kwargs)

    monkeypatch.setattr(LocalStorage, "move_in", move_in)
    monkeypatch.setattr(jobs, "finish", finish)
    return log


def losing_first_attempt(
    factory: sessionmaker[Session],
    job_id: str,
    compute: Callable[[JobContext], Any],
    run: Callable[[str], str],
) -> Callable[[JobContext], Any]:
    """``compute`` as attempt 1, after which the job is requeued (as the sweeper does after a
    heartbeat timeout) and ``run`` takes it to the end as attempt 2."""

    def stale(ctx: JobContext) -> Any:
        result = compute(ctx)
        with factory.begin() as s:
            assert jobs.requeue(s, job_id, 1)
        assert run(job_id) == "succeeded"
        return result

    return stale


def test_the_snapshot_job_publishes_before_its_transaction(
    uploaded: tuple[str, str],
    session_factory: sessionmaker[Session],
    storage: LocalStorage,
    transfers: list[str],
) -> None:
    snap_id, job_id = uploaded
    assert snapshot_glue.run(job_id) == "succeeded"
    snap = row(session_factory, Snapshot, snap_id)
    folder = f"{snap.storage_prefix}/reconstruction/{job_id}-1"
    assert transfers == [f"{folder}/cloud.ply", f"{folder}/cameras.json", "finish"]
    assert (snap.pointcloud_key, snap.cameras_key) == (
        f"{folder}/cloud.ply",
        f"{folder}/cameras.json",
    )
    assert storage.path(snap.pointcloud_key).read_bytes()[:3] == b"ply"
    assert published_folders(storage, f"{snap.storage_prefix}/reconstruction") == [f"{job_id}-1"]


def test_a_stale_attempt_leaves_the_winners_files_alone_and_nothing_behind(
    uploaded: tuple[str, str],
    session_factory: sessionmaker[Session],
    storage: LocalStorage,
) -> None:
    """Attempt 1 published, then its job was requeued (as the sweeper does after a
    heartbeat timeout) and attempt 2 ran it to the end; attempt 1 finds it lost the job.
    (A stale attempt that publishes after the winner committed: tests/app/api/test_s3_jobs.)"""
    snap_id, job_id = uploaded
    root = f"{row(session_factory, Snapshot, snap_id).storage_prefix}/reconstruction"

    def compute(ctx: JobContext) -> Any:
        outcome = snapshot_glue._compute(ctx)
        assert storage.path(f"{root}/{job_id}-1/cloud.ply").is_file()
        return outcome

    stale = losing_first_attempt(session_factory, job_id, compute, snapshot_glue.run)
    assert run_job(job_id, stale, snapshot_glue._persist, unpublish) == "lost"
    snap = row(session_factory, Snapshot, snap_id)
    assert snap.pointcloud_key == f"{root}/{job_id}-2/cloud.ply"
    assert storage.path(snap.pointcloud_key).is_file()
    assert storage.path(f"{root}/{job_id}-2/cameras.json").is_file()
    assert published_folders(storage, root) == [f"{job_id}-2"]
    job = row(session_factory, Job, job_id)
    assert (job.state, job.attempts) == (JobState.succeeded, 2)


def test_a_stale_comparison_attempt_leaves_the_winners_clusters(
    client: TestClient,
    keys: Keys,
    session_factory: sessionmaker[Session],
    sent_tasks: SentTasks,
    storage: LocalStorage,
) -> None:
    """The change clusters' points (whose change ids are new at each attempt) are served
    from the folder of the attempt that succeeded; a stale attempt's are removed."""
    env_id = make_env(client, keys)
    for scene in SCENES[:2]:
        snap_id = upload(client, keys, env_id, scene)
        assert snapshot_glue.run(snapshot_job(session_factory, snap_id)) == "succeeded"
    [(_, job_id)] = queued_comparisons(session_factory)

    stale = losing_first_attempt(
        session_factory, job_id, comparison_glue._compute, comparison_glue.run
    )
    assert run_job(job_id, stale, comparison_glue._persist, unpublish) == "lost"
    with session_factory() as s:
        comparison = s.scalars(select(Comparison).where(Comparison.job_id == job_id)).one()
        folder = change_clusters.comparison_folder(
            s.get_one(Snapshot, comparison.after_id).storage_prefix, comparison.id
        )
    assert published_folders(storage, folder) == [f"{job_id}-2"]
    assert not storage.exists(f"{folder}/{change_clusters.FILE}")  # nor the old place
    # served from the winner's folder (the fake comparison finds no cluster)
    r = client.get(f"/v1/comparisons/{comparison.id}/clusters", headers=keys.headers("read"))
    assert r.status_code == 200 and r.json() == {"clusters": []}, r.text


def test_a_failed_persist_removes_what_was_published(
    uploaded: tuple[str, str],
    session_factory: sessionmaker[Session],
    storage: LocalStorage,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    snap_id, job_id = uploaded

    def advance(*_args: Any) -> None:
        raise RuntimeError("the twin could not move on")

    monkeypatch.setattr(snapshot_glue.twin, "advance", advance)
    assert snapshot_glue.run(job_id) == "failed"
    snap = row(session_factory, Snapshot, snap_id)
    assert snap.pointcloud_key is None
    assert published_folders(storage, f"{snap.storage_prefix}/reconstruction") == []
    assert row(session_factory, Job, job_id).error_code == "InternalError"


def test_the_object_job_publishes_its_artefacts_before_its_transaction(
    client: TestClient,
    keys: Keys,
    session_factory: sessionmaker[Session],
    sent_tasks: SentTasks,
    storage: LocalStorage,
    transfers: list[str],
    tmp_path: Path,
) -> None:
    """Attempt 1 published, then lost the job to attempt 2: the winner's folder is recorded,
    attempt 1's removed."""
    mesh = tmp_path / "torus.ply"
    o3d.io.write_triangle_mesh(str(mesh), o3d.geometry.TriangleMesh.create_torus(0.2, 0.05))
    r = client.post(
        "/v1/objects",
        files={"file": ("torus.ply", mesh.read_bytes())},
        data={"name": "torus", "units": "m"},
        headers=keys.headers(),
    )
    assert r.status_code == 202, r.text
    object_id, job_id = r.json()["id"], r.json()["job"]["id"]
    root = object_glue.artifacts_root(object_id)

    stale = losing_first_attempt(session_factory, job_id, object_glue._compute, object_glue.run)
    assert run_job(job_id, stale, object_glue._persist, unpublish) == "lost"
    # each attempt moved its folder in before its final transaction began
    assert transfers == [f"{root}/{job_id}-1", f"{root}/{job_id}-2", "finish", "finish"]
    obj = row(session_factory, LibraryObject, object_id)
    assert obj.state == ObjectState.ready and obj.artifacts_key == f"{root}/{job_id}-2"
    assert storage.path(f"{obj.artifacts_key}/model.ply").is_file()
    assert published_folders(storage, root) == [f"{job_id}-2"]
