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


class SnapshotSource(StrEnum):
    """Where a snapshot's cloud comes from."""

    photos = "photos"  # reconstructed from an uploaded capture
    scan = "scan"  # read from an uploaded laser scan (E57, LAS, LAZ, PLY)


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


class TwinUpdate(StrEnum):
    """What the twin made of a snapshot, in seq order."""

    baseline = "baseline"  # the first reconstructed snapshot: nothing to compare it with
    applied = "applied"  # its automatic comparison's changes are in the twin
    skipped = "skipped"  # it failed or was cancelled before reconstructing


class TwinStatus(StrEnum):
    """Where an environment's twin stands against its snapshots."""

    current = "current"  # every snapshot is applied or skipped
    reconstructing = "reconstructing"  # waiting for the next snapshot to reconstruct
    comparing = "comparing"  # the next snapshot's automatic comparison is queued or running
    blocked = "blocked"  # that comparison failed or was cancelled: retry it to go on


class ChangeType(StrEnum):
    added = "added"
    removed = "removed"
    moved = "moved"
    swapped = "swapped"
    unidentified = "unidentified"


class TwinEdit(StrEnum):
    """A history record made through the API rather than by a comparison (its
    ``change_type`` is then one of these, else a :class:`ChangeType`)."""

    seeded = "seeded"  # created from the twin platform's own list (POST .../objects)
    corrected = "corrected"  # pose, class or external id set by hand (PATCH)
    retired = "retired"  # closed by hand (DELETE)
    inventoried = "inventoried"  # found by a snapshot's inventory (app.core.inventory)
    drifted = "drifted"  # an inventory's pose moved beyond the estimate's noise
    restored = "restored"  # reopened: its comparison removed it, its inventory shows it there


class EventType(StrEnum):
    snapshot_reconstructed = "snapshot.reconstructed"
    comparison_completed = "comparison.completed"
    twin_updated = "twin.updated"
    twin_blocked = "twin.blocked"
    job_failed = "job.failed"
    job_cancelled = "job.cancelled"


class DeliveryState(StrEnum):
    pending = "pending"
    succeeded = "succeeded"
    failed = "failed"


class UploadState(StrEnum):
    """A resumable (tus) upload: bytes arriving, the archive being ingested, a snapshot
    made, or refused (its error kept, its bytes gone)."""

    receiving = "receiving"
    processing = "processing"
    completed = "completed"
    failed = "failed"
