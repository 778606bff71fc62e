"""Deletion and retention: delete an environment or a snapshot (rows and files), apply the
retention policy, and clean up what killed processes leave in storage.

What deleting a snapshot does (docs/operations.md says the same to operators):

- its photos, labels, cameras and reconstruction files, its image rows (with their
  detections) and its jobs are deleted;
- every comparison it took part in (as ``before`` or ``after``) is deleted with its
  changes and its job: a comparison cannot be re-run or checked without both clouds;
- the twin's history stays whole: instances and their pose records keep their poses and
  the snapshot ids they were seen in; a pose record whose comparison was deleted keeps its
  snapshot and loses only the comparison link (``comparison`` becomes null);
- the snapshot row stays as a tombstone (id, seq, times, quality, state ``deleted``) so the
  history's snapshot references and ordering stay valid and sequence numbers are never
  reused; the API answers 404 for it and leaves it out of the snapshot list.

It is refused (409) while a job that uses it is queued or running (its reconstruction, a
comparison it takes part in, or a newer snapshot's reconstruction that may align to it),
and for the twin's current snapshot and the newest reconstructed one (see
:func:`protected`; delete the environment to drop everything). Afterwards the twin's chain
is advanced, so it skips the snapshot if it had not reached it yet.

Rows are deleted in the caller's transaction; files only once that transaction commits (a
rollback keeps them). Files whose rows are gone but which survived a crash between the
commit and the deletion are found by :func:`cleanup_files`.
"""

from __future__ import annotations

import logging
import os
import shutil
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any

from sqlalchemy import delete, event, or_, select, update
from sqlalchemy.orm import Session

from app.core import change_clusters, ingest, twin
from app.core.enums import JobKind, JobState, SnapshotState
from app.core.errors import Conflict, NotFound
from app.core.models import (
    Change,
    Comparison,
    Delivery,
    DeliveryAttempt,
    Environment,
    Event,
    InstancePose,
    Job,
    LibraryObject,
    Snapshot,
    SnapshotImage,
    TwinInstance,
    WebhookSubscription,
    utcnow,
)
from app.core.settings import Settings
from app.core.storage import Storage, check_key

log = logging.getLogger(__name__)

ACTIVE = (JobState.queued, JobState.running)
FINAL_SNAPSHOT_STATES = (SnapshotState.reconstructed, SnapshotState.failed, SnapshotState.cancelled)
_PENDING = "twindelta_files_to_delete"
# Snapshots one retention run deletes at most (the rest go in the next run), so one run never
# holds locks for long.
MAX_DELETIONS_PER_RUN = 200


# --- files, deleted after commit -------------------------------------------------------------


def delete_after_commit(session: Session, storage: Storage, key: str) -> None:
    """Delete ``key`` (a file or folder) once ``session``'s transaction commits."""
    check_key(key)  # refuse a bad key now, inside the transaction
    session.info.setdefault(_PENDING, []).append((storage, key))


@event.listens_for(Session, "after_commit")
def _delete_files_after_commit(session: Session) -> None:
    if session.in_nested_transaction():  # a released SAVEPOINT is not the commit
        return
    for storage, key in session.info.pop(_PENDING, []):
        try:
            storage.delete_prefix(key)
        except OSError:  # cleanup_files finds what is left
            log.exception("could not delete %s; the cleanup will retry", key)


@event.listens_for(Session, "after_soft_rollback")
def _keep_files_on_rollback(session: Session, previous_transaction: Any) -> None:
    if previous_transaction.parent is None:
        session.info.pop(_PENDING, None)


# --- deleting a snapshot ---------------------------------------------------------------------


def jobs_using(session: Session, snap: Snapshot) -> list[str]:
    """Ids of the queued or running jobs that use ``snap``: its own, those of comparisons it
    takes part in and, for a reconstructed snapshot, newer snapshots' reconstructions (which
    may align to its cloud). Locks them (PostgreSQL), so none starts while it is deleted."""
    in_comparison = select(Comparison.id).where(
        or_(Comparison.before_id == snap.id, Comparison.after_id == snap.id)
    )
    uses = [Job.snapshot_id == snap.id, Job.comparison_id.in_(in_comparison)]
    if snap.state == SnapshotState.reconstructed:
        newer = select(Snapshot.id).where(
            Snapshot.environment_id == snap.environment_id, Snapshot.seq > snap.seq
        )
        uses.append((Job.kind == JobKind.snapshot) & Job.snapshot_id.in_(newer))
    return list(
        session.scalars(
            select(Job.id).where(Job.state.in_(ACTIVE), or_(*uses)).with_for_update()
        ).all()
    )


def newest_reconstructed(session: Session, environment_id: str) -> Snapshot | None:
    """The newest reconstructed snapshot of an environment."""
    return session.scalar(
        select(Snapshot)
        .where(
            Snapshot.environment_id == environment_id,
            Snapshot.state == SnapshotState.reconstructed,
        )
        .order_by(Snapshot.seq.desc())
        .limit(1)
    )


def protected(session: Session, environment_id: str) -> set[str]:
    """Snapshots that are never deleted one by one: the one the twin stands at (the
    "before" of its next comparison, ``Environment.twin_snapshot_id``) and the newest
    reconstructed one (the twin is at it, or is on its way to it)."""
    env = session.get(Environment, environment_id)
    newest = newest_reconstructed(session, environment_id)
    return {
        snapshot_id
        for snapshot_id in (env.twin_snapshot_id if env else None, newest.id if newest else None)
        if snapshot_id is not None
    }


def delete_snapshot(session: Session, storage: Storage, snapshot_id: str) -> Snapshot:
    """Delete a snapshot's files, images, jobs and comparisons and leave its tombstone (see
    the module docstring); 404 when unknown or already deleted, 409 while a job uses it or
    when it is its environment's newest reconstructed snapshot."""
    snap = session.get(Snapshot, snapshot_id, with_for_update=True)
    if snap is None or snap.state == SnapshotState.deleted:
        raise NotFound(f"snapshot {snapshot_id} not found")
    busy = jobs_using(session, snap)
    if busy:
        raise Conflict(
            f"snapshot {snapshot_id} is in use by {len(busy)} queued or running job(s) "
            f"({', '.join(sorted(busy)[:5])}); cancel them or wait",
            code="JobsActive",
        )
    if snap.id in protected(session, snap.environment_id):
        raise Conflict(
            f"snapshot {snapshot_id} is the twin's current snapshot or the newest "
            "reconstructed one of its environment: the next capture is compared with it",
            code="SnapshotInUse",
        )
    _delete_snapshot_rows(session, storage, [snap.id])
    session.expire(snap, ["images"])  # deleted in bulk above
    now = utcnow()
    snap.state = SnapshotState.deleted
    snap.pointcloud_key = None
    snap.cameras_key = None
    snap.idempotency_key = None  # a retried upload makes a new snapshot, not this tombstone
    snap.request_digest = None
    snap.images_deleted_at = snap.images_deleted_at or now
    session.flush()
    delete_after_commit(session, storage, snap.storage_prefix)
    twin.advance(session, snap.environment_id)  # the chain skips it if it had not reached it
    return snap


def _delete_snapshot_rows(session: Session, storage: Storage, snapshot_ids: Sequence[str]) -> None:
    """Comparisons (with changes, jobs and files), jobs and image rows of the snapshots."""
    comparisons = session.execute(
        select(Comparison.id, Comparison.job_id).where(
            or_(Comparison.before_id.in_(snapshot_ids), Comparison.after_id.in_(snapshot_ids))
        )
    ).all()
    comparison_ids = [c for c, _ in comparisons]
    job_ids = [j for _, j in comparisons]
    job_ids += session.scalars(select(Job.id).where(Job.snapshot_id.in_(snapshot_ids))).all()
    _delete_comparisons(session, storage, comparison_ids)
    _delete(session, delete(Job).where(Job.id.in_(job_ids)))
    _delete(session, delete(SnapshotImage).where(SnapshotImage.snapshot_id.in_(snapshot_ids)))


def _delete_comparisons(session: Session, storage: Storage, comparison_ids: Sequence[str]) -> None:
    """The comparisons' rows, changes and jobs; their files (the change clusters, beside the
    after snapshot's, which may stay) go after the commit."""
    if not comparison_ids:
        return
    folders = session.execute(
        select(Comparison.id, Snapshot.storage_prefix)
        .join(Snapshot, Snapshot.id == Comparison.after_id)
        .where(Comparison.id.in_(comparison_ids))
    ).all()
    for comparison_id, after_prefix in folders:
        delete_after_commit(
            session, storage, change_clusters.comparison_folder(after_prefix, comparison_id)
        )
    session.execute(
        update(InstancePose)
        .where(InstancePose.comparison_id.in_(comparison_ids))
        .values(comparison_id=None)
        .execution_options(synchronize_session=False)
    )
    _delete(session, delete(Change).where(Change.comparison_id.in_(comparison_ids)))
    _delete(session, delete(Comparison).where(Comparison.id.in_(comparison_ids)))
    job_ids = select(Job.id).where(Job.comparison_id.in_(comparison_ids))
    _delete(session, delete(Job).where(Job.id.in_(job_ids)))


def _delete(session: Session, statement: Any) -> None:
    session.execute(statement.execution_options(synchronize_session=False))


# --- deleting an environment -----------------------------------------------------------------


def delete_environment(session: Session, storage: Storage, environment_id: str) -> None:
    """Delete an environment with every snapshot (and its files), comparison, job, twin
    record, event, delivery and environment-scoped webhook subscription; 404 when unknown,
    409 while any of its jobs is queued or running."""
    env = session.get(Environment, environment_id, with_for_update=True)
    if env is None:
        raise NotFound(f"environment {environment_id} not found")
    snapshot_ids = list(
        session.scalars(select(Snapshot.id).where(Snapshot.environment_id == env.id)).all()
    )
    busy = list(
        session.scalars(
            select(Job.id)
            .where(
                Job.state.in_(ACTIVE),
                or_(Job.environment_id == env.id, Job.snapshot_id.in_(snapshot_ids)),
            )
            .with_for_update()
        ).all()
    )
    if busy:
        raise Conflict(
            f"environment {environment_id} has {len(busy)} queued or running job(s) "
            f"({', '.join(sorted(busy)[:5])}); cancel them or wait",
            code="JobsActive",
        )
    prefixes = list(
        session.scalars(
            select(Snapshot.storage_prefix).where(Snapshot.environment_id == env.id)
        ).all()
    )
    instances = select(TwinInstance.id).where(TwinInstance.environment_id == env.id)
    _delete(session, delete(InstancePose).where(InstancePose.instance_id.in_(instances)))
    _delete(session, delete(TwinInstance).where(TwinInstance.environment_id == env.id))
    comparison_ids = list(
        session.scalars(select(Comparison.id).where(Comparison.environment_id == env.id)).all()
    )
    _delete_comparisons(session, storage, comparison_ids)
    _delete_snapshot_rows(session, storage, snapshot_ids)
    _delete(session, delete(Job).where(Job.environment_id == env.id))
    _delete(session, delete(Snapshot).where(Snapshot.environment_id == env.id))
    events = select(Event.id).where(Event.environment_id == env.id)
    subscriptions = select(WebhookSubscription.id).where(
        WebhookSubscription.environment_id == env.id
    )
    deliveries = select(Delivery.id).where(
        or_(Delivery.event_id.in_(events), Delivery.subscription_id.in_(subscriptions))
    )
    _delete(session, delete(DeliveryAttempt).where(DeliveryAttempt.delivery_id.in_(deliveries)))
    _delete(
        session,
        delete(Delivery).where(
            or_(Delivery.event_id.in_(events), Delivery.subscription_id.in_(subscriptions))
        ),
    )
    _delete(session, delete(Event).where(Event.environment_id == env.id))
    _delete(session, delete(WebhookSubscription).where(WebhookSubscription.id.in_(subscriptions)))
    session.delete(env)
    session.flush()
    for prefix in prefixes:
        delete_after_commit(session, storage, prefix)


# --- the retention policy --------------------------------------------------------------------


@dataclass(frozen=True)
class Policy:
    """``images_after_days``: delete the photos of snapshots older than this (0: never).
    ``keep_last_snapshots``: keep this many newest snapshots per environment (0: all).
    The settings give the default; an environment's ``options.retention`` overrides it."""

    images_after_days: float = 0.0
    keep_last_snapshots: int = 0

    @classmethod
    def from_settings(cls, settings: Settings) -> Policy:
        return cls(
            images_after_days=settings.retention_images_after_days,
            keep_last_snapshots=settings.retention_keep_last_snapshots,
        )

    def for_environment(self, options: dict[str, Any] | None) -> Policy:
        """This policy with the environment's own ``retention`` options in place."""
        own = (options or {}).get("retention") or {}
        return Policy(
            images_after_days=float(own.get("images_after_days", self.images_after_days)),
            keep_last_snapshots=int(own.get("keep_last_snapshots", self.keep_last_snapshots)),
        )


def apply_policy(
    session: Session, storage: Storage, policy: Policy, now: datetime | None = None
) -> dict[str, int]:
    """One retention pass over every environment, each with ``policy`` and its own
    overrides; returns counts. Snapshots in use (see :func:`delete_snapshot`) are skipped
    and tried again next time; at most MAX_DELETIONS_PER_RUN of each kind per pass."""
    now = now or utcnow()
    counts = {"snapshots_deleted": 0, "images_deleted": 0, "skipped_in_use": 0}
    for env in session.scalars(select(Environment).order_by(Environment.created_at)).all():
        own = policy.for_environment(env.options)
        if own.keep_last_snapshots > 0:
            _keep_last(session, storage, env, own.keep_last_snapshots, counts)
        if own.images_after_days > 0:
            cutoff = now - timedelta(days=own.images_after_days)
            _drop_images(session, storage, env.id, cutoff, now, counts)
    return counts


def _keep_last(
    session: Session, storage: Storage, env: Environment, keep: int, counts: dict[str, int]
) -> None:
    """Beyond the ``keep`` newest snapshots of ``env``, delete those that are final and that
    the twin has already taken into account (``seq <= twin_seq``: a snapshot the chain has
    not reached yet is never dropped unseen), except the protected ones."""
    live = session.scalars(
        select(Snapshot)
        .where(Snapshot.environment_id == env.id, Snapshot.state != SnapshotState.deleted)
        .order_by(Snapshot.seq.desc())
    ).all()
    keep_ids = protected(session, env.id)
    for snap in live[keep:]:
        if counts["snapshots_deleted"] >= MAX_DELETIONS_PER_RUN:
            return
        if (
            snap.state not in FINAL_SNAPSHOT_STATES
            or snap.id in keep_ids
            or snap.seq > (env.twin_seq or 0)
        ):
            continue
        try:
            delete_snapshot(session, storage, snap.id)
        except Conflict:  # refused before anything was written
            counts["skipped_in_use"] += 1
            continue
        counts["snapshots_deleted"] += 1


def _drop_images(
    session: Session,
    storage: Storage,
    environment_id: str,
    cutoff: datetime,
    now: datetime,
    counts: dict[str, int],
) -> None:
    """Delete the photos of the environment's final snapshots created before ``cutoff``.
    Comparisons use the cloud, the cameras and the detection rows, never the photos, so
    they still run."""
    room = MAX_DELETIONS_PER_RUN - counts["images_deleted"]
    if room <= 0:
        return
    old = session.scalars(
        select(Snapshot)
        .where(
            Snapshot.environment_id == environment_id,
            Snapshot.state.in_(FINAL_SNAPSHOT_STATES),
            Snapshot.images_deleted_at.is_(None),
            Snapshot.created_at < cutoff,
        )
        .order_by(Snapshot.created_at)
        .limit(room)
        .with_for_update(skip_locked=True)
    ).all()
    for snap in old:
        snap.images_deleted_at = now
        delete_after_commit(session, storage, f"{snap.storage_prefix}/images")
        counts["images_deleted"] += 1
    session.flush()


# --- cleanup of what killed processes leave ----------------------------------------------------


def cleanup_files(
    session: Session, storage: Storage, max_age_s: float, now: float | None = None
) -> dict[str, int]:
    """Remove from storage:

    - ``.work/<job>`` folders of jobs that are final or unknown (a worker killed before it
      cleaned up; queued and running jobs keep theirs, a requeued job resumes from it);
    - upload staging (``.tmp/<id>``) whose process is gone (:func:`ingest.sweep_staging`:
      its lock is free, or it has none and is an hour old), and half-written ``*.part``
      files untouched for ``max_age_s``;
    - ``snapshots/<id>`` folders whose snapshot is deleted, and those with no row at all
      once older than ``max_age_s`` (an upload killed between storing and committing);
      photos of snapshots whose photos retention already deleted; a live snapshot's
      ``comparisons/<id>`` folders whose comparison is gone;
    - ``objects/<id>`` folders with no row, once older than ``max_age_s``.
    Returns counts by kind.
    """
    now = time.time() if now is None else now
    counts = {"work": 0, "staging": 0, "partial": 0, "snapshots": 0, "objects": 0}
    counts["work"] = sweep_work(session, storage)
    counts["staging"] = ingest.sweep_staging(storage)
    _cleanup_snapshot_folders(session, storage, max_age_s, now, counts)
    newest = storage.folders("objects")
    names = sorted(newest)
    if names:
        known = {
            object_id
            for chunk in _chunks(names, 500)
            for object_id in session.scalars(
                select(LibraryObject.id).where(LibraryObject.id.in_(chunk))
            )
        }
        for name in names:
            if name not in known and now - newest[name] > max_age_s:
                storage.delete_prefix(f"objects/{name}")
                counts["objects"] += 1
    # write_stream's unfinished writes (models)
    counts["partial"] = storage.remove_partial("objects", now - max_age_s)
    return counts


def sweep_work(session: Session, storage: Storage) -> int:
    """Remove this host's ``.work/<job>`` scratch folders of jobs that are final or unknown
    (a worker killed before it cleaned up; queued and running jobs keep theirs, a requeued
    job resumes from it); returns how many."""
    work = storage.scratch_path(".work")
    names = _children(work)
    states: dict[str, str] = {}
    for chunk in _chunks(names, 500):
        states.update(session.execute(select(Job.id, Job.state).where(Job.id.in_(chunk))).all())
    removed = 0
    for name in names:
        state = states.get(name)
        if state is None or JobState(state).is_final:
            shutil.rmtree(work / name, ignore_errors=True)
            removed += 1
    return removed


def _cleanup_snapshot_folders(
    session: Session, storage: Storage, max_age_s: float, now: float, counts: dict[str, int]
) -> None:
    newest = storage.folders("snapshots")
    names = sorted(newest)
    rows: dict[str, tuple[str, datetime | None]] = {}
    for chunk in _chunks(names, 500):
        for snapshot_id, state, images_deleted_at in session.execute(
            select(Snapshot.id, Snapshot.state, Snapshot.images_deleted_at).where(
                Snapshot.id.in_(chunk)
            )
        ):
            rows[snapshot_id] = (state, images_deleted_at)
    for name in names:
        prefix = f"snapshots/{name}"
        row = rows.get(name)
        if row is None:
            if now - newest[name] > max_age_s:
                storage.delete_prefix(prefix)
                counts["snapshots"] += 1
        elif row[0] == SnapshotState.deleted:
            storage.delete_prefix(prefix)
            counts["snapshots"] += 1
        else:
            if row[1] is not None and storage.exists(f"{prefix}/images"):
                storage.delete_prefix(f"{prefix}/images")
                counts["snapshots"] += 1
            counts["snapshots"] += _cleanup_comparison_folders(
                session, storage, f"{prefix}/comparisons"
            )


def _cleanup_comparison_folders(session: Session, storage: Storage, folder: str) -> int:
    """Remove the ``comparisons/<id>`` folders under ``folder`` whose comparison row is gone
    (its files are written only while the row exists); returns how many."""
    names = sorted(storage.folders(folder))
    if not names:
        return 0
    known = set(session.scalars(select(Comparison.id).where(Comparison.id.in_(names))).all())
    for name in names:
        if name not in known:
            storage.delete_prefix(f"{folder}/{name}")
    return len(names) - len(known)


def _children(folder: Path) -> list[str]:
    try:
        return sorted(entry.name for entry in os.scandir(folder) if entry.is_dir())
    except FileNotFoundError:
        return []


def _chunks(items: Sequence[str], size: int) -> Iterable[Sequence[str]]:
    for start in range(0, len(items), size):
        yield items[start : start + size]


# --- disk usage ------------------------------------------------------------------------------


@dataclass(frozen=True)
class DiskUsage:
    total_bytes: int
    used_bytes: int
    free_bytes: int


def disk_usage(root: Path) -> DiskUsage:
    """The file system holding ``root`` (the storage folder): size, used and free bytes (free
    as an unprivileged process may use it)."""
    usage = shutil.disk_usage(root)
    return DiskUsage(total_bytes=usage.total, used_bytes=usage.used, free_bytes=usage.free)
