"""Deletion, the retention policy and the cleanup of what killed processes leave, on a real
history: three reconstructed snapshots, two comparisons, one twin instance with its poses,
files in storage, events and webhook deliveries."""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path

import numpy as np
import pytest
from sqlalchemy import func, select
from sqlalchemy.orm import Session, sessionmaker

from app.core import change_clusters, queue, retention, snapshots, webhooks
from app.core.enums import ComparisonState, JobKind, JobState, SnapshotState
from app.core.errors import Conflict, NotFound
from app.core.models import (
    Change,
    Comparison,
    Delivery,
    Environment,
    Event,
    InstancePose,
    Job,
    LibraryObject,
    Snapshot,
    SnapshotImage,
    TwinInstance,
    WebhookSubscription,
    new_id,
    utcnow,
)
from app.core.settings import get_settings
from app.core.storage import LocalStorage

POSE = [[1.0, 0, 0, 0.1], [0, 1.0, 0, 0.2], [0, 0, 1.0, 0], [0, 0, 0, 1.0]]


@dataclass
class History:
    env: str
    snaps: list[str]  # seq 1, 2, 3
    comparisons: list[str]  # 1→2, 2→3
    comparison_jobs: list[str]
    snapshot_jobs: list[str]
    instance: str
    other_env: str
    other_snap: str


def _files(storage: LocalStorage, prefix: str) -> None:
    storage.write_bytes(f"{prefix}/images/a.jpg", b"\xff\xd8 photo")
    storage.write_bytes(f"{prefix}/labels/a.txt", b"0 0.5 0.5 0.2 0.2\n")
    storage.write_bytes(f"{prefix}/reconstruction/cloud.ply", b"ply cloud")
    storage.write_bytes(f"{prefix}/reconstruction/cameras.json", b"{}")


def _snapshot(s: Session, storage: LocalStorage, env_id: str, seq: int, age_days: float) -> str:
    snap_id = new_id()
    prefix = f"snapshots/{snap_id}"
    s.add(
        Snapshot(
            id=snap_id,
            environment_id=env_id,
            seq=seq,
            state=SnapshotState.reconstructed,
            idempotency_key=f"key-{seq}",
            storage_prefix=prefix,
            n_images=1,
            pointcloud_key=f"{prefix}/reconstruction/cloud.ply",
            cameras_key=f"{prefix}/reconstruction/cameras.json",
            created_at=utcnow() - timedelta(days=age_days),
        )
    )
    s.flush()
    s.add(
        SnapshotImage(
            snapshot_id=snap_id,
            name="a.jpg",
            file_key=f"{prefix}/images/a.jpg",
            labels_key=f"{prefix}/labels/a.txt",
            width=32,
            height=24,
            size_bytes=11,
            detections=[{"class_id": 0, "cx": 0.5, "cy": 0.5, "w": 0.2, "h": 0.2}],
        )
    )
    _files(storage, prefix)
    return snap_id


def _job(s: Session, kind: JobKind, state: JobState = JobState.succeeded, **subject: str) -> str:
    job = Job(kind=kind, task_name=f"{kind}.x", state=state, **subject)
    s.add(job)
    s.flush()
    return job.id


def _comparison(s: Session, env_id: str, before: str, after: str) -> tuple[str, str]:
    comparison_id = new_id()
    job_id = _job(s, JobKind.comparison, environment_id=env_id, comparison_id=comparison_id)
    s.add(
        Comparison(
            id=comparison_id,
            environment_id=env_id,
            before_id=before,
            after_id=after,
            job_id=job_id,
            automatic=True,
            state=ComparisonState.succeeded,
        )
    )
    s.flush()
    s.add(Change(comparison_id=comparison_id, position=0, type="added", object_name="bowl"))
    return comparison_id, job_id


@pytest.fixture
def storage(data_dir: Path) -> LocalStorage:
    return LocalStorage(get_settings().resolved_storage_dir)


@pytest.fixture
def history(session_factory: sessionmaker[Session], storage: LocalStorage) -> History:
    with session_factory.begin() as s:
        env = Environment(name=f"hall-{new_id()[:8]}", classes=["bowl"], options={})
        other = Environment(name=f"yard-{new_id()[:8]}", classes=["bowl"], options={})
        s.add_all([env, other])
        s.flush()
        snaps = [_snapshot(s, storage, env.id, seq, age) for seq, age in ((1, 30), (2, 20), (3, 1))]
        snapshot_jobs = [
            _job(s, JobKind.snapshot, environment_id=env.id, snapshot_id=snap) for snap in snaps
        ]
        c12, j12 = _comparison(s, env.id, snaps[0], snaps[1])
        c23, j23 = _comparison(s, env.id, snaps[1], snaps[2])
        env.twin_seq, env.twin_snapshot_id = 3, snaps[2]  # the twin took all three in
        instance = TwinInstance(
            environment_id=env.id,
            object_name="bowl",
            pose=POSE,
            since_snapshot_id=snaps[2],
            created_snapshot_id=snaps[1],
        )
        s.add(instance)
        s.flush()
        s.add_all(
            [
                InstancePose(
                    instance_id=instance.id,
                    snapshot_id=snaps[1],
                    comparison_id=c12,
                    change_type="added",
                    pose=POSE,
                ),
                InstancePose(
                    instance_id=instance.id,
                    snapshot_id=snaps[2],
                    comparison_id=c23,
                    change_type="moved",
                    pose=POSE,
                ),
            ]
        )
        event = Event(type="snapshot.reconstructed", environment_id=env.id, data={})
        s.add(event)
        subscription = webhooks.create_subscription(
            s,
            get_settings(),
            url="https://8.8.8.8/hook",
            event_types=None,
            environment_id=env.id,
        )
        s.flush()
        s.add(Delivery(subscription_id=subscription.id, event_id=event.id, ordering_key="k"))
        other_snap = _snapshot(s, storage, other.id, 1, 30)
        _job(s, JobKind.snapshot, environment_id=other.id, snapshot_id=other_snap)
    return History(
        env=env.id,
        snaps=snaps,
        comparisons=[c12, c23],
        comparison_jobs=[j12, j23],
        snapshot_jobs=snapshot_jobs,
        instance=instance.id,
        other_env=other.id,
        other_snap=other_snap,
    )


def _count(s: Session, model: type, *where: object) -> int:
    return int(s.scalar(select(func.count()).select_from(model).where(*where)) or 0)


def test_delete_snapshot_removes_files_rows_and_its_comparisons_keeps_the_twin_history(
    session_factory: sessionmaker[Session], storage: LocalStorage, history: History
) -> None:
    first, second, third = history.snaps
    with session_factory.begin() as s:
        retention.delete_snapshot(s, storage, first)
    assert not storage.exists(f"snapshots/{first}")
    assert storage.exists(f"snapshots/{second}/images/a.jpg")
    with session_factory.begin() as s:
        with pytest.raises(NotFound):
            snapshots.get(s, first)
        assert [x.id for x in snapshots.history(s, history.env)] == [third, second]
        tombstone = s.get(Snapshot, first)
        assert tombstone is not None and tombstone.state == SnapshotState.deleted
        assert tombstone.seq == 1 and tombstone.pointcloud_key is None
        assert tombstone.idempotency_key is None
        assert _count(s, SnapshotImage, SnapshotImage.snapshot_id == first) == 0
        assert _count(s, Job, Job.id == history.snapshot_jobs[0]) == 0
        # the comparison 1→2 is gone with its changes and job; 2→3 stays
        assert s.get(Comparison, history.comparisons[0]) is None
        assert _count(s, Change, Change.comparison_id == history.comparisons[0]) == 0
        assert _count(s, Job, Job.id == history.comparison_jobs[0]) == 0
        assert s.get(Comparison, history.comparisons[1]) is not None
        # the twin's history keeps both poses; the first loses only its comparison link
        poses = s.scalars(
            select(InstancePose)
            .where(InstancePose.instance_id == history.instance)
            .order_by(InstancePose.change_type)
        ).all()
        assert [(p.change_type, p.snapshot_id, p.comparison_id) for p in poses] == [
            ("added", second, None),
            ("moved", third, history.comparisons[1]),
        ]
        assert s.get(TwinInstance, history.instance) is not None
    # the middle one may go too; the twin still lists the instance
    with session_factory.begin() as s:
        retention.delete_snapshot(s, storage, second)
        with pytest.raises(NotFound):
            retention.delete_snapshot(s, storage, second)
    with session_factory.begin() as s:
        assert s.get(Comparison, history.comparisons[1]) is None
        assert _count(s, InstancePose, InstancePose.instance_id == history.instance) == 2


def test_newest_reconstructed_snapshot_is_never_deleted(
    session_factory: sessionmaker[Session], storage: LocalStorage, history: History
) -> None:
    with session_factory.begin() as s, pytest.raises(Conflict) as refused:
        retention.delete_snapshot(s, storage, history.snaps[2])
    assert refused.value.code == "SnapshotInUse"
    assert storage.exists(f"snapshots/{history.snaps[2]}/reconstruction/cloud.ply")


def test_the_twins_current_snapshot_is_never_deleted(
    session_factory: sessionmaker[Session], storage: LocalStorage, history: History
) -> None:
    """The chain is held at seq 2 (its comparison with seq 3 failed, say): seq 2 is the
    "before" of the retry and stays; seq 3, not yet taken into account, stays too."""
    with session_factory.begin() as s:
        env = s.get_one(Environment, history.env)
        env.twin_seq, env.twin_snapshot_id = 2, history.snaps[1]
        s.get_one(Comparison, history.comparisons[1]).state = ComparisonState.failed
        s.get_one(Job, history.comparison_jobs[1]).state = JobState.failed
    with session_factory.begin() as s, pytest.raises(Conflict) as refused:
        retention.delete_snapshot(s, storage, history.snaps[1])
    assert refused.value.code == "SnapshotInUse"
    with session_factory.begin() as s:
        counts = retention.apply_policy(s, storage, retention.Policy(keep_last_snapshots=1))
    assert counts["snapshots_deleted"] == 1  # seq 1 only
    with session_factory.begin() as s:
        assert [x.seq for x in snapshots.history(s, history.env)] == [3, 2]


def test_delete_snapshot_refused_while_a_job_uses_it(
    session_factory: sessionmaker[Session], storage: LocalStorage, history: History
) -> None:
    with session_factory.begin() as s:
        s.get_one(Job, history.comparison_jobs[1]).state = JobState.running
    with session_factory.begin() as s, pytest.raises(Conflict) as refused:
        retention.delete_snapshot(s, storage, history.snaps[1])
    assert refused.value.code == "JobsActive"
    assert history.comparison_jobs[1] in refused.value.detail
    with session_factory.begin() as s:
        s.get_one(Job, history.comparison_jobs[1]).state = JobState.succeeded
        # a newer capture still being reconstructed may align to any reconstructed one
        newer = _snapshot(s, storage, history.env, 4, 0)
        s.get_one(Snapshot, newer).state = SnapshotState.processing
        running = _job(s, JobKind.snapshot, JobState.queued, snapshot_id=newer)
    with session_factory.begin() as s, pytest.raises(Conflict) as refused:
        retention.delete_snapshot(s, storage, history.snaps[0])
    assert running in refused.value.detail
    assert storage.exists(f"snapshots/{history.snaps[0]}/images/a.jpg")


def test_files_stay_when_the_transaction_rolls_back(
    session_factory: sessionmaker[Session], storage: LocalStorage, history: History
) -> None:
    with pytest.raises(RuntimeError), session_factory.begin() as s:
        retention.delete_snapshot(s, storage, history.snaps[0])
        raise RuntimeError("the request failed after the delete")
    assert storage.exists(f"snapshots/{history.snaps[0]}/reconstruction/cloud.ply")
    with session_factory.begin() as s:
        assert snapshots.get(s, history.snaps[0]).state == SnapshotState.reconstructed


def test_delete_environment_removes_everything_of_it_and_nothing_else(
    session_factory: sessionmaker[Session], storage: LocalStorage, history: History
) -> None:
    with session_factory.begin() as s:
        retention.delete_environment(s, storage, history.env)
    for snap in history.snaps:
        assert not storage.exists(f"snapshots/{snap}")
    assert storage.exists(f"snapshots/{history.other_snap}/images/a.jpg")
    with session_factory.begin() as s:
        assert s.get(Environment, history.env) is None
        for model in (Snapshot, Comparison, Job, TwinInstance, Event, WebhookSubscription):
            assert _count(s, model, model.environment_id == history.env) == 0, model
        assert _count(s, SnapshotImage, SnapshotImage.snapshot_id.in_(history.snaps)) == 0
        assert _count(s, InstancePose, InstancePose.instance_id == history.instance) == 0
        assert _count(s, Change, Change.comparison_id.in_(history.comparisons)) == 0
        assert _count(s, Delivery, Delivery.ordering_key == "k") == 0
        assert s.get(Environment, history.other_env) is not None
        assert snapshots.get(s, history.other_snap).pointcloud_key
        with pytest.raises(NotFound):
            retention.delete_environment(s, storage, history.env)


def test_delete_environment_refused_while_a_job_is_queued(
    session_factory: sessionmaker[Session], storage: LocalStorage, history: History
) -> None:
    with session_factory.begin() as s:
        s.get_one(Job, history.snapshot_jobs[2]).state = JobState.queued
    with session_factory.begin() as s, pytest.raises(Conflict) as refused:
        retention.delete_environment(s, storage, history.env)
    assert refused.value.code == "JobsActive"
    with session_factory.begin() as s:
        assert s.get(Environment, history.env) is not None
    assert storage.exists(f"snapshots/{history.snaps[0]}/images/a.jpg")


def test_policy_keeps_the_last_snapshots_and_the_newest_reconstructed(
    session_factory: sessionmaker[Session], storage: LocalStorage, history: History
) -> None:
    with session_factory.begin() as s:
        failed = _snapshot(s, storage, history.env, 4, 0)
        s.get_one(Snapshot, failed).state = SnapshotState.failed
    policy = retention.Policy(keep_last_snapshots=1)
    with session_factory.begin() as s:
        counts = retention.apply_policy(s, storage, policy)
    # keeps seq 4 (the last one) and seq 3 (the newest reconstructed: the twin's reference)
    assert counts["snapshots_deleted"] == 2
    with session_factory.begin() as s:
        assert [x.seq for x in snapshots.history(s, history.env)] == [4, 3]
        assert [x.seq for x in snapshots.history(s, history.other_env)] == [1]
    for snap in history.snaps[:2]:
        assert not storage.exists(f"snapshots/{snap}")
    with session_factory.begin() as s:
        assert retention.apply_policy(s, storage, policy)["snapshots_deleted"] == 0


def test_policy_skips_snapshots_in_use(
    session_factory: sessionmaker[Session], storage: LocalStorage, history: History
) -> None:
    with session_factory.begin() as s:
        s.get_one(Job, history.comparison_jobs[0]).state = JobState.running
    with session_factory.begin() as s:
        counts = retention.apply_policy(s, storage, retention.Policy(keep_last_snapshots=1))
    assert counts == {"snapshots_deleted": 0, "images_deleted": 0, "skipped_in_use": 2}
    assert storage.exists(f"snapshots/{history.snaps[0]}/images/a.jpg")


def test_policy_drops_old_photos_and_keeps_clouds(
    session_factory: sessionmaker[Session], storage: LocalStorage, history: History
) -> None:
    policy = retention.Policy(images_after_days=10)
    with session_factory.begin() as s:
        counts = retention.apply_policy(s, storage, policy)
    # seq 1 and 2 (30 and 20 days old) and the other environment's (30 days)
    assert counts["images_deleted"] == 3
    for snap in (*history.snaps[:2], history.other_snap):
        assert not storage.exists(f"snapshots/{snap}/images")
        assert storage.exists(f"snapshots/{snap}/reconstruction/cloud.ply")
        assert storage.exists(f"snapshots/{snap}/labels/a.txt")
    assert storage.exists(f"snapshots/{history.snaps[2]}/images/a.jpg")
    with session_factory.begin() as s:
        first = snapshots.get(s, history.snaps[0])
        assert first.images_deleted_at is not None
        assert first.state == SnapshotState.reconstructed and first.pointcloud_key
        # the detections a comparison needs are rows and stay
        assert _count(s, SnapshotImage, SnapshotImage.snapshot_id == first.id) == 1
        assert retention.apply_policy(s, storage, policy)["images_deleted"] == 0


def _age(path: Path, seconds: float) -> None:
    when = time.time() - seconds
    for root, dirs, files in os.walk(path):
        for name in (*dirs, *files):
            os.utime(os.path.join(root, name), (when, when))
    os.utime(path, (when, when))


def test_cleanup_removes_leftovers_of_killed_processes(
    session_factory: sessionmaker[Session], storage: LocalStorage, history: History
) -> None:
    root = storage.root
    with session_factory.begin() as s:
        running = _job(s, JobKind.snapshot, JobState.running)
        requeued = _job(s, JobKind.snapshot, JobState.queued)
        obj = LibraryObject(name="bowl", filename="m.ply", file_key="k", size_bytes=1)
        s.add(obj)
        s.flush()
        object_id = obj.id
    work = {
        "final": history.snapshot_jobs[0],
        "unknown": new_id(),
        "running": running,
        "requeued": requeued,
    }
    for job_id in work.values():
        (root / ".work" / job_id / "reconstruct").mkdir(parents=True)
        (root / ".work" / job_id / "reconstruct" / "db.sqlite").write_bytes(b"x")
    hour = 3600.0
    for name, age in (("old", 2 * hour), ("fresh", 0.0)):
        (root / ".tmp" / name / "images").mkdir(parents=True)
        (root / ".tmp" / name / "images" / "a.jpg").write_bytes(b"x")
        _age(root / ".tmp" / name, age)
    # a killed upload's moved-in folder with no row, old and fresh; a stray tombstone folder
    for name, age in (("orphan-old", 2 * hour), ("orphan-fresh", 0.0)):
        (root / "snapshots" / name / "images").mkdir(parents=True)
        _age(root / "snapshots" / name, age)
    for name, age in ((object_id, 2 * hour), ("gone-old", 2 * hour), ("gone-fresh", 0.0)):
        (root / "objects" / name).mkdir(parents=True)
        (root / "objects" / name / ".model.ply.0123.part").write_bytes(b"half")
        _age(root / "objects" / name, age)
    with session_factory.begin() as s:
        counts = retention.cleanup_files(s, storage, max_age_s=hour)
    assert not (root / ".work" / work["final"]).exists()
    assert not (root / ".work" / work["unknown"]).exists()
    assert (root / ".work" / work["running"] / "reconstruct" / "db.sqlite").exists()
    assert (root / ".work" / work["requeued"] / "reconstruct" / "db.sqlite").exists()
    assert not (root / ".tmp" / "old").exists() and (root / ".tmp" / "fresh").exists()
    assert not (root / "snapshots" / "orphan-old").exists()
    assert (root / "snapshots" / "orphan-fresh").exists()
    for snap in history.snaps:
        assert (root / "snapshots" / snap / "images" / "a.jpg").exists()
    assert (root / "objects" / object_id).is_dir()
    assert not (root / "objects" / object_id / ".model.ply.0123.part").exists()
    assert not (root / "objects" / "gone-old").exists()
    assert (root / "objects" / "gone-fresh" / ".model.ply.0123.part").exists()
    assert counts == {"work": 2, "staging": 1, "partial": 1, "snapshots": 1, "objects": 1}


def test_cleanup_finishes_deletions_a_crash_interrupted(
    session_factory: sessionmaker[Session], storage: LocalStorage, history: History
) -> None:
    """Rows committed, process killed before the files went: the cleanup deletes them."""
    with session_factory.begin() as s:
        s.get_one(Snapshot, history.snaps[0]).state = SnapshotState.deleted
        s.get_one(Snapshot, history.snaps[1]).images_deleted_at = utcnow()
    with session_factory.begin() as s:
        retention.cleanup_files(s, storage, max_age_s=3600)
    assert not storage.exists(f"snapshots/{history.snaps[0]}")
    assert not storage.exists(f"snapshots/{history.snaps[1]}/images")
    assert storage.exists(f"snapshots/{history.snaps[1]}/reconstruction/cloud.ply")


def test_retention_runs_on_the_beat_schedule(data_dir: Path) -> None:
    settings = get_settings()
    config = queue.celery_config(settings)
    entry = next(
        e for e in config["beat_schedule"].values() if e["task"] == "maintenance.retention"
    )
    assert entry["schedule"] == settings.retention_interval_s
    # beside the sweeper, on the worker that runs beat's periodic tasks
    assert queue.TASK_QUEUES["maintenance.retention"] == queue.TASK_QUEUES["maintenance.sweep"]


def test_retention_task_applies_the_settings_policy_and_cleans_up(
    session_factory: sessionmaker[Session],
    storage: LocalStorage,
    history: History,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from workers.maintenance_tasks import retention as retention_task

    monkeypatch.setenv("TWINDELTA_RETENTION_KEEP_LAST_SNAPSHOTS", "1")
    monkeypatch.setenv("TWINDELTA_RETENTION_IMAGES_AFTER_DAYS", "10")
    get_settings.cache_clear()
    (storage.root / ".work" / history.snapshot_jobs[2]).mkdir(parents=True)
    counts = retention_task()
    assert counts["snapshots_deleted"] == 2 and counts["work"] == 1
    assert counts["images_deleted"] == 1  # the other environment's 30-day-old photos
    assert not storage.exists(f"snapshots/{history.other_snap}/images")
    assert not storage.exists(f"snapshots/{history.snaps[0]}")
    assert storage.exists(f"snapshots/{history.snaps[2]}/images/a.jpg")


def test_an_environments_own_policy_overrides_the_settings(
    session_factory: sessionmaker[Session], storage: LocalStorage, history: History
) -> None:
    with session_factory.begin() as s:
        s.get_one(Environment, history.env).options = {"retention": {"keep_last_snapshots": 2}}
        s.get_one(Environment, history.other_env).options = {"retention": {"images_after_days": 0}}
    policy = retention.Policy(images_after_days=10, keep_last_snapshots=1)
    with session_factory.begin() as s:
        counts = retention.apply_policy(s, storage, policy)
    # env: keeps 2 (seq 3, 2), drops the photos of seq 2 (20 days); other: keeps its photos
    assert counts["snapshots_deleted"] == 1 and counts["images_deleted"] == 1
    with session_factory.begin() as s:
        assert [x.seq for x in snapshots.history(s, history.env)] == [3, 2]
    assert not storage.exists(f"snapshots/{history.snaps[1]}/images")
    assert storage.exists(f"snapshots/{history.other_snap}/images/a.jpg")


def _store_clusters(storage: LocalStorage, after: str, comparison_id: str) -> str:
    """A one-cluster clusters.npz for ``comparison_id`` beside ``after``; returns its key."""
    key = change_clusters.clusters_key(f"snapshots/{after}", comparison_id)
    points = np.zeros((4, 3), np.float32)
    change_clusters.write(
        storage, key, [change_clusters.StoredCluster(0, "added", None, 4, points)]
    )
    return key


def test_policy_deletes_the_cluster_files_of_the_comparisons_it_deletes(
    session_factory: sessionmaker[Session], storage: LocalStorage, history: History
) -> None:
    """Seq 1 goes: its comparison 1→2 goes with the clusters stored beside seq 2, which stays."""
    first, second, third = history.snaps
    gone = _store_clusters(storage, second, history.comparisons[0])
    kept = _store_clusters(storage, third, history.comparisons[1])
    with session_factory.begin() as s:
        counts = retention.apply_policy(s, storage, retention.Policy(keep_last_snapshots=2))
    assert counts["snapshots_deleted"] == 1
    assert not storage.exists(f"snapshots/{first}")
    assert not storage.exists(gone.rsplit("/", 1)[0])
    assert storage.exists(f"snapshots/{second}/reconstruction/cloud.ply")
    assert storage.exists(kept)


def test_cleanup_removes_cluster_files_whose_comparison_is_gone(
    session_factory: sessionmaker[Session], storage: LocalStorage, history: History
) -> None:
    """A clusters.npz left by a deletion that ran before comparisons took their files along."""
    orphan = _store_clusters(storage, history.snaps[2], new_id())
    kept = _store_clusters(storage, history.snaps[2], history.comparisons[1])
    with session_factory.begin() as s:
        counts = retention.cleanup_files(s, storage, max_age_s=3600)
    assert not storage.exists(orphan.rsplit("/", 1)[0]) and storage.exists(kept)
    assert counts["snapshots"] == 1
