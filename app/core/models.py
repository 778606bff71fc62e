"""SQLAlchemy 2 models: one table per noun of the contract.

Times are timezone-aware UTC. JSON columns hold the contract's nested shapes (poses as 4×4
nested lists in metres, quality figures, identification tables) verbatim.
"""

from __future__ import annotations

import uuid
from datetime import UTC, datetime
from typing import Any

from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    DateTime,
    Float,
    ForeignKey,
    Index,
    Integer,
    String,
    Text,
    UniqueConstraint,
    text,
)
from sqlalchemy.engine import Dialect
from sqlalchemy.orm import Mapped, mapped_column, relationship
from sqlalchemy.types import TypeDecorator

from app.core.db import Base
from app.core.enums import (
    ComparisonState,
    DeliveryState,
    JobKind,
    JobState,
    ObjectState,
    SnapshotSource,
    SnapshotState,
    UploadState,
)


def new_id() -> str:
    return str(uuid.uuid4())


def utcnow() -> datetime:
    return datetime.now(UTC)


Json = dict[str, Any]


class _UtcDateTime(TypeDecorator[datetime]):
    """``DateTime(timezone=True)`` that always hands back an aware UTC datetime.

    PostgreSQL stores ``timestamptz`` and returns aware values; SQLite stores text without
    an offset and returns naive ones, which the API would show without a timezone (not an
    RFC 3339 ``date-time``). Values are converted to UTC on the way in (a naive value is
    taken as UTC) and marked UTC on the way out. The column type is unchanged."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        return value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)

    def process_result_value(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        return value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)


UtcDateTime = _UtcDateTime()


class ApiKey(Base):
    __tablename__ = "api_keys"

    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=new_id)
    name: Mapped[str] = mapped_column(String(200))
    # a short non-secret id ("td_" + the first 8 hex digits of ``id``); generated tokens
    # start with it, so a person can tell which key a token is without any of its secret
    prefix: Mapped[str] = mapped_column(String(16), index=True)
    key_hash: Mapped[str] = mapped_column(String(64), unique=True)
    scopes: Mapped[list[str]] = mapped_column(JSON)
    # the environments the key reaches; None: every one
    environment_ids: Mapped[list[str] | None] = mapped_column(JSON)
    created_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)
    last_used_at: Mapped[datetime | None] = mapped_column(UtcDateTime)
    revoked_at: Mapped[datetime | None] = mapped_column(UtcDateTime)


class Environment(Base):
    __tablename__ = "environments"

    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=new_id)
    name: Mapped[str] = mapped_column(String(200), unique=True)
    classes: Mapped[list[str]] = mapped_column(JSON)
    reference: Mapped[Json | None] = mapped_column(JSON)
    options: Mapped[Json] = mapped_column(JSON, default=dict)
    created_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)
    # The twin's place in the snapshot sequence (app.core.twin.advance): every snapshot up
    # to ``twin_seq`` is applied or skipped; ``twin_snapshot_id`` is the newest one applied
    # (the "before" of the next automatic comparison); ``twin_blocked_by`` the failed
    # automatic comparison that holds the chain, once announced.
    twin_seq: Mapped[int] = mapped_column(Integer, default=0, server_default="0")
    twin_snapshot_id: Mapped[str | None] = mapped_column(String(36))
    twin_blocked_by: Mapped[str | None] = mapped_column(String(36))


class LibraryObject(Base):
    __tablename__ = "library_objects"
    __table_args__ = (
        Index(
            "uq_library_objects_live_name",
            "name",
            unique=True,
            postgresql_where=text("deleted_at IS NULL"),
            sqlite_where=text("deleted_at IS NULL"),
        ),
    )

    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=new_id)
    name: Mapped[str] = mapped_column(String(200))
    state: Mapped[ObjectState] = mapped_column(String(20), default=ObjectState.processing)
    units: Mapped[str] = mapped_column(String(4), default="m")
    symmetry_requested: Mapped[Json] = mapped_column(JSON, default=dict)
    symmetry: Mapped[Json | None] = mapped_column(JSON)
    diameter_m: Mapped[float | None] = mapped_column(Float)
    n_points: Mapped[int | None] = mapped_column(Integer)
    filename: Mapped[str] = mapped_column(String(255))
    file_key: Mapped[str] = mapped_column(String(500))
    artifacts_key: Mapped[str | None] = mapped_column(String(500))
    size_bytes: Mapped[int] = mapped_column(Integer)
    created_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)
    deleted_at: Mapped[datetime | None] = mapped_column(UtcDateTime)


class Snapshot(Base):
    __tablename__ = "snapshots"
    __table_args__ = (
        UniqueConstraint("environment_id", "seq", name="uq_snapshots_env_seq"),
        UniqueConstraint("environment_id", "idempotency_key", name="uq_snapshots_idempotency"),
    )

    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=new_id)
    environment_id: Mapped[str] = mapped_column(
        ForeignKey("environments.id", ondelete="CASCADE"), index=True
    )
    seq: Mapped[int] = mapped_column(Integer)
    state: Mapped[SnapshotState] = mapped_column(String(20), default=SnapshotState.uploaded)
    # photos: reconstructed from a capture; scan: read from an uploaded laser scan
    source: Mapped[SnapshotSource] = mapped_column(
        String(10), default=SnapshotSource.photos, server_default=SnapshotSource.photos.value
    )
    idempotency_key: Mapped[str | None] = mapped_column(String(200))
    request_digest: Mapped[str | None] = mapped_column(String(64))
    storage_prefix: Mapped[str] = mapped_column(String(500))
    n_images: Mapped[int] = mapped_column(Integer, default=0)
    n_detections: Mapped[int] = mapped_column(Integer, default=0)
    upload_bytes: Mapped[int] = mapped_column(BigInteger, default=0)  # up to max_upload_bytes
    has_cameras: Mapped[bool] = mapped_column(Boolean, default=False)
    quality: Mapped[Json] = mapped_column(JSON, default=dict)
    pointcloud_key: Mapped[str | None] = mapped_column(String(500))
    cameras_key: Mapped[str | None] = mapped_column(String(500))
    created_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)
    reconstructed_at: Mapped[datetime | None] = mapped_column(UtcDateTime)
    # what the twin made of it: baseline | applied | skipped (None until its turn)
    twin_update: Mapped[str | None] = mapped_column(String(20))
    # set when retention deleted the photos (the cloud, cameras and detections stay)
    images_deleted_at: Mapped[datetime | None] = mapped_column(UtcDateTime)
    # the inventory's summary (supports, counts, timings, rejected segments); None: no
    # inventory taken (not reconstructed yet, a scan, or no library object ready)
    inventory: Mapped[Json | None] = mapped_column(JSON)

    images: Mapped[list[SnapshotImage]] = relationship(
        back_populates="snapshot", order_by="SnapshotImage.name", cascade="all, delete-orphan"
    )


class SnapshotImage(Base):
    """One uploaded photo and its detections (recorded by the worker's ingest stage)."""

    __tablename__ = "snapshot_images"
    __table_args__ = (UniqueConstraint("snapshot_id", "name", name="uq_snapshot_images_name"),)

    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=new_id)
    snapshot_id: Mapped[str] = mapped_column(
        ForeignKey("snapshots.id", ondelete="CASCADE"), index=True
    )
    name: Mapped[str] = mapped_column(String(255))
    file_key: Mapped[str] = mapped_column(String(500))
    labels_key: Mapped[str | None] = mapped_column(String(500))
    width: Mapped[int] = mapped_column(Integer)
    height: Mapped[int] = mapped_column(Integer)
    size_bytes: Mapped[int] = mapped_column(Integer)
    detections: Mapped[list[Json]] = mapped_column(JSON, default=list)
    verified_at: Mapped[datetime | None] = mapped_column(UtcDateTime)

    snapshot: Mapped[Snapshot] = relationship(back_populates="images")


class Job(Base):
    """The single truth for a unit of background work: state, stage, progress, error."""

    __tablename__ = "jobs"
    __table_args__ = (Index("ix_jobs_state_kind", "state", "kind"),)

    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=new_id)
    kind: Mapped[JobKind] = mapped_column(String(20))
    task_name: Mapped[str] = mapped_column(String(100))
    state: Mapped[JobState] = mapped_column(String(20), default=JobState.queued)
    stage: Mapped[str | None] = mapped_column(String(100))
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    preset: Mapped[str] = mapped_column(String(50), default="default")
    options: Mapped[Json] = mapped_column(JSON, default=dict)
    result: Mapped[Json] = mapped_column(JSON, default=dict)
    error_code: Mapped[str | None] = mapped_column(String(100))
    error_detail: Mapped[str | None] = mapped_column(Text)
    cancel_requested: Mapped[bool] = mapped_column(Boolean, default=False)
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    sends: Mapped[int] = mapped_column(Integer, default=0)
    worker: Mapped[str | None] = mapped_column(String(200))
    environment_id: Mapped[str | None] = mapped_column(
        ForeignKey("environments.id", ondelete="CASCADE"), index=True
    )
    snapshot_id: Mapped[str | None] = mapped_column(
        ForeignKey("snapshots.id", ondelete="CASCADE"), index=True
    )
    comparison_id: Mapped[str | None] = mapped_column(String(36), index=True)
    object_id: Mapped[str | None] = mapped_column(
        ForeignKey("library_objects.id", ondelete="CASCADE"), index=True
    )
    created_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)
    enqueued_at: Mapped[datetime | None] = mapped_column(UtcDateTime)
    started_at: Mapped[datetime | None] = mapped_column(UtcDateTime)
    heartbeat_at: Mapped[datetime | None] = mapped_column(UtcDateTime)
    finished_at: Mapped[datetime | None] = mapped_column(UtcDateTime)


class Comparison(Base):
    __tablename__ = "comparisons"

    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=new_id)
    environment_id: Mapped[str] = mapped_column(
        ForeignKey("environments.id", ondelete="CASCADE"), index=True
    )
    before_id: Mapped[str] = mapped_column(ForeignKey("snapshots.id", ondelete="CASCADE"))
    after_id: Mapped[str] = mapped_column(ForeignKey("snapshots.id", ondelete="CASCADE"))
    job_id: Mapped[str] = mapped_column(ForeignKey("jobs.id"))
    automatic: Mapped[bool] = mapped_column(Boolean, default=False)
    state: Mapped[ComparisonState] = mapped_column(String(20), default=ComparisonState.queued)
    options: Mapped[Json] = mapped_column(JSON, default=dict)
    distances: Mapped[Json] = mapped_column(JSON, default=dict)
    clusters: Mapped[list[Json]] = mapped_column(JSON, default=list)
    applied_to_state: Mapped[bool] = mapped_column(Boolean, default=False)
    created_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)
    completed_at: Mapped[datetime | None] = mapped_column(UtcDateTime)
    applied_at: Mapped[datetime | None] = mapped_column(UtcDateTime)

    changes: Mapped[list[Change]] = relationship(
        back_populates="comparison", order_by="Change.position", cascade="all, delete-orphan"
    )


class Change(Base):
    __tablename__ = "changes"

    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=new_id)
    comparison_id: Mapped[str] = mapped_column(
        ForeignKey("comparisons.id", ondelete="CASCADE"), index=True
    )
    position: Mapped[int] = mapped_column(Integer)
    type: Mapped[str] = mapped_column(String(20))
    object_name: Mapped[str | None] = mapped_column(String(200))
    object_id: Mapped[str | None] = mapped_column(String(36))  # the library object, if known
    instance_id: Mapped[str | None] = mapped_column(String(36))
    pose: Mapped[list[list[float]] | None] = mapped_column(JSON)
    previous_pose: Mapped[list[list[float]] | None] = mapped_column(JSON)
    replaced_object: Mapped[str | None] = mapped_column(String(200))
    replaced_instance_id: Mapped[str | None] = mapped_column(String(36))
    centroid_env: Mapped[list[float] | None] = mapped_column(JSON)
    identification: Mapped[Json | None] = mapped_column(JSON)
    cluster: Mapped[Json | None] = mapped_column(JSON)
    pose_quality: Mapped[Json | None] = mapped_column(JSON)

    comparison: Mapped[Comparison] = relationship(back_populates="changes")


class TwinInstance(Base):
    """One physical object instance in an environment's twin, open until removed.

    ``external_id`` is the twin platform's own id of the object (set by seeding or a
    correction), unique among an environment's open instances. An instance seeded before
    the twin reflected any snapshot has no ``created_snapshot_id`` / ``since_snapshot_id``
    (it stands from the start)."""

    __tablename__ = "twin_instances"
    __table_args__ = (
        Index(
            "uq_twin_instances_open_external_id",
            "environment_id",
            "external_id",
            unique=True,
            postgresql_where=text("closed_snapshot_id IS NULL AND external_id IS NOT NULL"),
            sqlite_where=text("closed_snapshot_id IS NULL AND external_id IS NOT NULL"),
        ),
    )

    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=new_id)
    environment_id: Mapped[str] = mapped_column(
        ForeignKey("environments.id", ondelete="CASCADE"), index=True
    )
    object_name: Mapped[str] = mapped_column(String(200))
    object_id: Mapped[str | None] = mapped_column(
        ForeignKey("library_objects.id", ondelete="SET NULL")
    )
    pose: Mapped[list[list[float]] | None] = mapped_column(JSON)
    pose_quality: Mapped[Json | None] = mapped_column(JSON)
    centroid_env: Mapped[list[float] | None] = mapped_column(JSON)
    external_id: Mapped[str | None] = mapped_column(String(200))
    since_snapshot_id: Mapped[str | None] = mapped_column(ForeignKey("snapshots.id"))
    created_snapshot_id: Mapped[str | None] = mapped_column(ForeignKey("snapshots.id"))
    closed_snapshot_id: Mapped[str | None] = mapped_column(ForeignKey("snapshots.id"))
    created_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)
    closed_at: Mapped[datetime | None] = mapped_column(UtcDateTime)


class InstancePose(Base):
    """The history of an instance: one row per pose it has had."""

    __tablename__ = "instance_poses"

    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=new_id)
    instance_id: Mapped[str] = mapped_column(
        ForeignKey("twin_instances.id", ondelete="CASCADE"), index=True
    )
    # None: a seed or correction made before the twin reflected any snapshot
    snapshot_id: Mapped[str | None] = mapped_column(ForeignKey("snapshots.id"))
    comparison_id: Mapped[str | None] = mapped_column(ForeignKey("comparisons.id"))
    change_type: Mapped[str] = mapped_column(String(20))
    pose: Mapped[list[list[float]] | None] = mapped_column(JSON)
    centroid_env: Mapped[list[float] | None] = mapped_column(JSON)
    created_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)


class SnapshotObject(Base):
    """One library object a snapshot's inventory found (workers/pipeline/inventory), with
    the twin instance it was taken for (None until the twin reached the snapshot, or when
    the twin did not take it)."""

    __tablename__ = "snapshot_objects"

    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=new_id)
    snapshot_id: Mapped[str] = mapped_column(
        ForeignKey("snapshots.id", ondelete="CASCADE"), index=True
    )
    position: Mapped[int] = mapped_column(Integer)
    object_name: Mapped[str] = mapped_column(String(200))
    object_id: Mapped[str | None] = mapped_column(
        ForeignKey("library_objects.id", ondelete="SET NULL")
    )
    # 4×4 env_from_object, metres; None when the class has no prepared model
    pose: Mapped[list[list[float]] | None] = mapped_column(JSON)
    pose_quality: Mapped[Json | None] = mapped_column(JSON)
    # the compare stage's figures of its class: metric, iou, overlaps, occurrences
    identification: Mapped[Json] = mapped_column(JSON)
    centroid_env: Mapped[list[float]] = mapped_column(JSON)
    support: Mapped[str | None] = mapped_column(String(50))
    instance_id: Mapped[str | None] = mapped_column(
        ForeignKey("twin_instances.id", ondelete="SET NULL"), index=True
    )
    created_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)


class WebhookSubscription(Base):
    __tablename__ = "webhook_subscriptions"

    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=new_id)
    url: Mapped[str] = mapped_column(String(2000))
    event_types: Mapped[list[str]] = mapped_column(JSON)
    environment_id: Mapped[str | None] = mapped_column(
        ForeignKey("environments.id", ondelete="CASCADE"), index=True
    )
    # Signing secrets encrypted at rest (app/core/secretbox.py). After a rotation the
    # previous one signs too until ``previous_secret_expires_at``.
    secret_encrypted: Mapped[str] = mapped_column(String(500))
    previous_secret_encrypted: Mapped[str | None] = mapped_column(String(500))
    previous_secret_expires_at: Mapped[datetime | None] = mapped_column(UtcDateTime)
    active: Mapped[bool] = mapped_column(Boolean, default=True)
    created_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)
    deactivated_at: Mapped[datetime | None] = mapped_column(UtcDateTime)
    # the body's shape (app.core.webhooks.adapters.WebhookFormat): cloudevents, or one
    # platform adapter's patch per changed twin instance
    format: Mapped[str] = mapped_column(
        String(40), default="cloudevents", server_default="cloudevents"
    )


class Event(Base):
    """A CloudEvent, written in the same transaction as the state change that causes it."""

    __tablename__ = "events"

    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=new_id)
    type: Mapped[str] = mapped_column(String(100), index=True)
    environment_id: Mapped[str | None] = mapped_column(
        ForeignKey("environments.id", ondelete="CASCADE"), index=True
    )
    subject: Mapped[str | None] = mapped_column(String(200))
    data: Mapped[Json] = mapped_column(JSON)
    created_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)


class Delivery(Base):
    """One event to one subscription; retried on a schedule, every attempt logged.

    Deliveries sharing an ``ordering_key`` (subscription and environment) are sent one at a
    time in ``(seq, id)`` order: only the oldest pending one (the head) may be claimed.
    ``attempts`` counts every attempt ever claimed and is the fencing token of the one in
    flight; ``run_attempts`` counts those of the current run (a redelivery starts a new run
    on the retry schedule). ``locked_until`` is the lease of an attempt in flight;
    ``dispatched_at`` says when a deliver message was last sent for it.
    """

    __tablename__ = "deliveries"
    __table_args__ = (
        Index("ix_deliveries_state_next", "state", "next_attempt_at"),
        Index("ix_deliveries_key_state_seq", "ordering_key", "state", "seq"),
    )

    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=new_id)
    subscription_id: Mapped[str] = mapped_column(
        ForeignKey("webhook_subscriptions.id", ondelete="CASCADE"), index=True
    )
    event_id: Mapped[str] = mapped_column(ForeignKey("events.id", ondelete="CASCADE"), index=True)
    ordering_key: Mapped[str] = mapped_column(String(100))
    seq: Mapped[int] = mapped_column(Integer, default=0)
    state: Mapped[DeliveryState] = mapped_column(String(20), default=DeliveryState.pending)
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    run_attempts: Mapped[int] = mapped_column(Integer, default=0)
    next_attempt_at: Mapped[datetime | None] = mapped_column(UtcDateTime)
    locked_until: Mapped[datetime | None] = mapped_column(UtcDateTime)
    dispatched_at: Mapped[datetime | None] = mapped_column(UtcDateTime)
    last_status_code: Mapped[int | None] = mapped_column(Integer)
    last_error: Mapped[str | None] = mapped_column(Text)
    created_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)
    finished_at: Mapped[datetime | None] = mapped_column(UtcDateTime)
    # Platform adapter deliveries (one per changed twin instance): the instance, and the body
    # rendered at fan-out (a JSON Patch list or a merge patch object). Both None for a
    # CloudEvents delivery, whose body is rendered from its event.
    instance_id: Mapped[str | None] = mapped_column(String(36))
    # the platform's id of the twin an adapter body addresses (external id, else instance id)
    twin_id: Mapped[str | None] = mapped_column(String(200))
    payload: Mapped[Json | None] = mapped_column(JSON)


class DeliveryAttempt(Base):
    __tablename__ = "delivery_attempts"

    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=new_id)
    delivery_id: Mapped[str] = mapped_column(
        ForeignKey("deliveries.id", ondelete="CASCADE"), index=True
    )
    number: Mapped[int] = mapped_column(Integer)
    attempted_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)
    status_code: Mapped[int | None] = mapped_column(Integer)
    latency_ms: Mapped[float | None] = mapped_column(Float)
    response_excerpt: Mapped[str | None] = mapped_column(Text)
    error: Mapped[str | None] = mapped_column(Text)


class ResumableUpload(Base):
    """One resumable (tus) upload of a capture archive. Its bytes so far are the stored
    objects ``<storage_key>/<part>`` named by ``parts`` in order (one per PATCH), together
    ``offset_bytes`` long; once the last byte arrived the archive is ingested like a
    single-request upload and the parts go."""

    __tablename__ = "resumable_uploads"
    __table_args__ = (Index("ix_resumable_uploads_env_key", "environment_id", "idempotency_key"),)

    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=new_id)
    environment_id: Mapped[str] = mapped_column(
        ForeignKey("environments.id", ondelete="CASCADE"), index=True
    )
    state: Mapped[UploadState] = mapped_column(String(20), default=UploadState.receiving)
    length: Mapped[int] = mapped_column(BigInteger)  # bytes, Upload-Length
    filename: Mapped[str] = mapped_column(String(255))
    idempotency_key: Mapped[str | None] = mapped_column(String(200))
    sha256: Mapped[str | None] = mapped_column(String(64))  # of the whole archive, if declared
    storage_key: Mapped[str] = mapped_column(String(500))
    offset_bytes: Mapped[int] = mapped_column(BigInteger, default=0)  # Upload-Offset
    parts: Mapped[list[str]] = mapped_column(JSON, default=list)  # names under storage_key
    # while processing: when the request ingesting it last said it is alive
    heartbeat_at: Mapped[datetime | None] = mapped_column(UtcDateTime)
    # set when the upload became a snapshot (not foreign keys: the rows outlive neither)
    snapshot_id: Mapped[str | None] = mapped_column(String(36))
    job_id: Mapped[str | None] = mapped_column(String(36))
    error_status: Mapped[int | None] = mapped_column(Integer)
    error_code: Mapped[str | None] = mapped_column(String(100))
    error_detail: Mapped[str | None] = mapped_column(Text)
    created_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)
    expires_at: Mapped[datetime] = mapped_column(UtcDateTime, index=True)
    completed_at: Mapped[datetime | None] = mapped_column(UtcDateTime)
