"""How the API answers a request that created (or, for a repeated ``Idempotency-Key``,
found again) something: ``Location`` and ``Idempotent-Replayed``."""

from __future__ import annotations

from fastapi import Response

from app.api.schemas.jobs import JobRead
from app.api.schemas.snapshots import SnapshotAccepted, SnapshotRead
from app.core.ingest import Ingested


def point_to(response: Response, location: str, *, replayed: bool) -> None:
    """``Location: location``, and ``Idempotent-Replayed: true`` when the request repeated
    an earlier one and nothing new was made."""
    response.headers["Location"] = location
    if replayed:
        response.headers["Idempotent-Replayed"] = "true"


def snapshot_accepted(response: Response, result: Ingested) -> SnapshotAccepted:
    """The 202 answer of a snapshot upload (photos, scan): the snapshot and its job, with
    ``Location`` the job."""
    point_to(response, f"/v1/jobs/{result.job.id}", replayed=not result.created)
    return SnapshotAccepted(
        snapshot=SnapshotRead.of(result.snapshot, result.job, None),
        job=JobRead.of(result.job),
    )
