"""The upload: validate a staged capture, insert its snapshot (the environment's next seq),
move its files in and queue its job, once; a replayed Idempotency-Key returns the first."""

from __future__ import annotations

import os
from collections.abc import Iterator, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sqlalchemy import event, func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from app.core import environments, jobs, snapshots
from app.core.enums import JobKind, SnapshotState
from app.core.errors import (
    Conflict,
)
from app.core.ingest.archives import _stage_archive
from app.core.ingest.common import _SEQ_RETRIES, CAMERAS_NAME, CLASSES_NAME, TASK, _invalid
from app.core.ingest.images import probe_image
from app.core.ingest.parsers import parse_cameras, parse_classes, parse_detections
from app.core.ingest.staging import UploadPart, _add, _Staged, _Staging, _staging_dir, sweep_staging
from app.core.models import Environment, Job, Snapshot, new_id
from app.core.settings import Settings
from app.core.storage import Storage


@dataclass(frozen=True)
class UploadFiles:
    """The files of one upload: loose ``images`` (with optional ``detections`` and
    ``cameras``), or one ``archive`` holding the same files."""

    images: Sequence[UploadPart] = ()
    detections: Sequence[UploadPart] = ()
    cameras: UploadPart | None = None
    archive: UploadPart | None = None

    def check(self) -> None:
        """InvalidUpload (422) for both kinds at once, or neither."""
        loose = bool(self.images or self.detections or self.cameras is not None)
        if self.archive is not None and loose:
            raise _invalid(
                "InvalidUpload", "send either an archive or images/detections/cameras, not both"
            )
        if self.archive is None and not self.images:
            raise _invalid("InvalidUpload", "no images: send 'images' files or one 'archive'")


@dataclass(frozen=True)
class Ingested:
    """The outcome of an upload: the snapshot, its job, and whether this request made them
    (False for an idempotent replay)."""

    snapshot: Snapshot
    job: Job
    created: bool


@dataclass(frozen=True)
class _Checked:
    n_detections: int


def _validate(staging: _Staging, classes: Sequence[str]) -> _Checked:
    """Every check that needs the whole capture: counts, orphans, images, detections,
    cameras and classes.txt."""
    settings = staging.settings
    if len(staging.images) < settings.min_images:
        raise _invalid(
            "TooFewImages",
            f"{len(staging.images)} images; a snapshot needs at least {settings.min_images}",
        )
    for stem, labels in sorted(staging.labels.items()):
        if stem not in staging.image_stems:
            raise _invalid("OrphanDetections", f"{labels.where}: no image with the stem {stem!r}")
    # Decoders release the GIL: probe a few images at once; the first error in upload order.
    pool = ThreadPoolExecutor(max_workers=min(4, os.cpu_count() or 1))
    try:
        probes = [
            pool.submit(
                _probe_path, image, settings.max_image_pixels, settings.max_image_decoded_bytes
            )
            for image in staging.images.values()
        ]
        for probe in probes:
            probe.result()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
    n_detections = 0
    for labels in staging.labels.values():
        with labels.path.open("rb") as fh:
            n_detections += len(
                parse_detections(fh, labels.where, classes, settings.max_detection_lines)
            )
    if staging.cameras is not None:
        with staging.cameras.path.open("rb") as fh:
            parse_cameras(fh, staging.cameras.where, staging.images.keys())
    classes_file = staging.root / ".classes.txt"
    if classes_file.exists():
        with classes_file.open("rb") as fh:
            parse_classes(fh, CLASSES_NAME, classes)
        classes_file.unlink()
    return _Checked(n_detections=n_detections)


def _probe_path(image: _Staged, max_pixels: int, max_decoded: int) -> tuple[int, int]:
    with image.path.open("rb") as fh:
        return probe_image(fh, image.where, max_pixels, max_decoded)


# --- the upload -----------------------------------------------------------------------------


def create_snapshot(
    session: Session,
    storage: Storage,
    settings: Settings,
    environment_id: str,
    files: UploadFiles,
    *,
    idempotency_key: str | None = None,
    lookup: sessionmaker[Session] | None = None,
) -> Ingested:
    """Validate and store an uploaded capture, insert its snapshot (state ``uploaded``, the
    environment's next ``seq``) and queue ``snapshot.process`` after commit.

    ``files`` are loose files (``images``, ``detections``, ``cameras``) or one ``archive``.
    Errors are DomainErrors naming the file and line; nothing is stored when one is raised; a
    full disk is a 507 ``InsufficientStorage``.

    ``lookup`` opens short read-only sessions for what is read before the files are checked
    (the environment, an earlier request with the same ``Idempotency-Key``). The API gives
    one, so that ``session`` touches the database only for the insert: on SQLite its write
    lock is then held for milliseconds, not while the files are staged and checked. Without
    it, ``session`` does the reads too.
    """
    with _reading(session, lookup) as reader:
        env = environments.get(reader, environment_id)
        env_id, classes = env.id, list(env.classes)
    files.check()
    if idempotency_key is not None and not 0 < len(idempotency_key) <= 200:
        raise _invalid("InvalidUpload", "Idempotency-Key: 1 to 200 characters")

    sweep_staging(storage)
    with _staging_dir(storage) as staging_dir:
        staging = _Staging(root=staging_dir, settings=settings)
        _stage_files(staging, files)
        digest = staging.digest()
        replay = replay_of(session, lookup, env_id, idempotency_key, digest)
        if replay is not None:
            return replay
        checked = _validate(staging, classes)
        fields = {
            "n_images": len(staging.images),
            "n_detections": checked.n_detections,
            "upload_bytes": staging.n_bytes,
            "has_cameras": staging.cameras is not None,
        }
        return insert_snapshot(
            session, storage, env_id, staging.root, fields, idempotency_key, digest
        )


def _stage_files(staging: _Staging, files: UploadFiles) -> None:
    """Stream the upload's files into the staging folder, each by its role."""
    if files.archive is not None:
        _stage_archive(staging, files.archive)
        return
    for part in files.images:
        _add(staging, part.filename, part.filename, part.source, "images")
    for part in files.detections:
        _add(staging, part.filename, part.filename, part.source, "detections")
    if files.cameras is not None:
        where = files.cameras.filename or CAMERAS_NAME
        _add(staging, CAMERAS_NAME, where, files.cameras.source, "cameras")


@contextmanager
def _reading(session: Session, lookup: sessionmaker[Session] | None) -> Iterator[Session]:
    """``session``, or a short read-only session of ``lookup`` (closed, never committed)."""
    if lookup is None:
        yield session
        return
    with lookup() as reader:
        yield reader


def replay_of(
    session: Session,
    lookup: sessionmaker[Session] | None,
    environment_id: str,
    key: str | None,
    digest: str,
) -> Ingested | None:
    """The earlier upload with ``Idempotency-Key`` ``key`` (:func:`_replay`), looked up
    first with ``lookup``'s short session and then, when found, again in ``session`` (so the
    answer's rows belong to it); None without a key or when it is new."""
    if key is None:
        return None
    with _reading(session, lookup) as reader:
        replay = _replay(reader, environment_id, key, digest)
    if replay is not None and lookup is not None:
        replay = _replay(session, environment_id, key, digest)
    return replay


def _replay(session: Session, environment_id: str, key: str, digest: str) -> Ingested | None:
    """The snapshot an earlier request with this key made, when the files are the same;
    409 ``IdempotencyKeyReused`` when they differ; None when the key is new."""
    snap = session.scalar(
        select(Snapshot).where(
            Snapshot.environment_id == environment_id, Snapshot.idempotency_key == key
        )
    )
    if snap is None:
        return None
    if snap.request_digest != digest:
        raise Conflict(
            f"Idempotency-Key {key!r} was used for snapshot {snap.id} with different files",
            code="IdempotencyKeyReused",
        )
    job = snapshots.job_of(session, snap.id)
    if job is None:  # the job is created in the snapshot's transaction; never expected
        raise Conflict(f"snapshot {snap.id} has no job", code="IdempotencyKeyReused")
    return Ingested(snapshot=snap, job=job, created=False)


def insert_snapshot(
    session: Session,
    storage: Storage,
    env_id: str,
    root: Path,
    fields: Mapping[str, Any],
    idempotency_key: str | None,
    digest: str,
) -> Ingested:
    """Move the checked files at ``root`` in under ``snapshots/<id>``, then insert the
    upload's snapshot (state ``uploaded``, the environment's next ``seq``, the columns in
    ``fields``; ``cameras_key`` when ``has_cameras``) and its job. The photo and the scan
    uploads both end here. The files move first, before the environment is locked: with S3
    storage that is an upload, and other uploads to the environment must not wait for it. A
    concurrent upload that takes the seq or the ``Idempotency-Key`` first makes it look
    again (the key's replay, whose files then go, or the next seq), at most
    ``_SEQ_RETRIES`` times: then 409 ``ConcurrentUpload``. 404 when the environment went
    while the files were checked."""
    snapshot_id = new_id()
    prefix = f"snapshots/{snapshot_id}"
    try:
        storage.move_in(root, prefix)
        ingested = _insert_rows(session, env_id, snapshot_id, fields, idempotency_key, digest)
    except BaseException:
        storage.delete_prefix(prefix)
        raise
    if not ingested.created:  # a replay: the earlier snapshot's files serve it
        storage.delete_prefix(prefix)
        return ingested
    # The files are in place before the row is committed (a reader never sees a row without
    # its files); if the transaction rolls back instead (a failed commit, an error after
    # this), they go with it.
    session.info.setdefault(_MOVED_IN, []).append((storage, prefix))
    return ingested


def _insert_rows(
    session: Session,
    env_id: str,
    snapshot_id: str,
    fields: Mapping[str, Any],
    idempotency_key: str | None,
    digest: str,
) -> Ingested:
    """The snapshot row and its job (:func:`insert_snapshot`), or the replay of the key."""
    # Serialise uploads to one environment (PostgreSQL row lock; SQLite has one writer).
    session.execute(select(Environment.id).where(Environment.id == env_id).with_for_update())
    environments.get(session, env_id)
    prefix = f"snapshots/{snapshot_id}"
    snap: Snapshot | None = None
    for _ in range(_SEQ_RETRIES):
        if idempotency_key is not None:
            replay = _replay(session, env_id, idempotency_key, digest)
            if replay is not None:
                return replay
        latest = session.scalar(
            select(func.max(Snapshot.seq)).where(Snapshot.environment_id == env_id)
        )
        candidate = Snapshot(
            id=snapshot_id,
            environment_id=env_id,
            seq=(latest or 0) + 1,
            state=SnapshotState.uploaded,
            idempotency_key=idempotency_key,
            request_digest=digest,
            storage_prefix=prefix,
            cameras_key=f"{prefix}/{CAMERAS_NAME}" if fields.get("has_cameras") else None,
            **fields,
        )
        try:
            with session.begin_nested():
                session.add(candidate)
                session.flush()
        except IntegrityError:  # a concurrent upload took the seq or the key: look again
            continue
        snap = candidate
        break
    if snap is None:
        raise Conflict(
            f"environment {env_id}: too many concurrent uploads, try again",
            code="ConcurrentUpload",
        )
    job = jobs.create(session, JobKind.snapshot, TASK, environment_id=env_id, snapshot_id=snap.id)
    return Ingested(snapshot=snap, job=job, created=True)


_MOVED_IN = "twindelta_ingest_moved_in"


@event.listens_for(Session, "after_commit")
def _keep_moved_in(session: Session) -> None:
    if not session.in_nested_transaction():
        session.info.pop(_MOVED_IN, None)


@event.listens_for(Session, "after_soft_rollback")
def _remove_moved_in(session: Session, previous_transaction: Any) -> None:
    if previous_transaction.parent is None:  # the outermost rollback, not a SAVEPOINT's
        for storage, prefix in session.info.pop(_MOVED_IN, []):
            storage.delete_prefix(prefix)
