"""String enums stored in the database and shown in the API."""

from __future__ import annotations

from enum import StrEnum


class Scope(StrEnum):
    capture = "capture"
    read = "read"
    admin = "admin"
    metrics = "metrics"


class JobState(StrEnum):
    queued = "queued"
    running = "running"
    succeeded = "succeeded"
    failed = "failed"
    cancelled = "cancelled"

    @property
    def is_final(self) -> bool:
        return self in {JobState.succeeded, JobState.failed, JobState.cancelled}


class JobKind(StrEnum):
    snapshot = "snapshot"
    comparison = "comparison"
    object = "object"


class SnapshotState(StrEnum):
    uploaded = "uploaded"
    processing = "processing"
    reconstructed = "reconstructed"
    failed = "failed"
    cancelled = "cancelled"
    deleted = "deleted"  # a tombstone: files, images, jobs and comparisons are gone


class ObjectState(StrEnum):
    processing = "processing"
    ready = "ready"
    failed = "failed"
    cancelled = "cancelled"


class ComparisonState(StrEnum):
    queued = "queued"
    running = "running"
    succeeded = "succeeded"
    failed = "failed"
    cancelled = "cancelled"


class ChangeType(StrEnum):
    added = "added"
    removed = "removed"
    moved = "moved"
    swapped = "swapped"
    unidentified = "unidentified"


class EventType(StrEnum):
    snapshot_reconstructed = "snapshot.reconstructed"
    comparison_completed = "comparison.completed"
    job_failed = "job.failed"
    job_cancelled = "job.cancelled"


class DeliveryState(StrEnum):
    pending = "pending"
    succeeded = "succeeded"
    failed = "failed"
