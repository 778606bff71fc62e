"""The snapshot job: re-read the upload (image sizes, detections) → reconstruct the cloud
in the environment frame → record quality → move the twin's chain on (app.core.twin.advance:
the automatic comparison with the newest earlier reconstructed snapshot, once every earlier
snapshot is settled)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sqlalchemy.orm import Session

from app.core import environments, events, ingest, snapshots, twin
from app.core.db import transaction
from app.core.enums import EventType, SnapshotSource, SnapshotState
from app.core.models import utcnow
from workers import scan_snapshot
from workers.pipeline.reconstruct.cameras import load_cameras
from workers.pipeline.reconstruct.options import options_from_preset
from workers.pipeline.reconstruct.stage import ReconstructionResult, reconstruct
from workers.progress import weighted
from workers.runner import JobContext, run_job

# Rough shares of a snapshot job's time (30 views at 800×600 on 2 cores), for one overall
# progress figure.
STAGE_WEIGHTS = {
    "ingest": 2,
    "features": 12,
    "matching": 18,
    "mapping": 14,
    "sparse": 5,
    "markers": 3,
    "load": 2,
    "neighbours": 1,
    "dense": 2,
    "stereo": 20,
    "consistency": 10,
    "fusion": 8,
    "alignment": 3,
    "write": 1,
}


@dataclass(frozen=True)
class SnapshotInputs:
    snapshot_id: str
    environment_id: str
    prefix: str
    classes: list[str]
    reference: dict[str, Any] | None
    options: dict[str, Any]
    previous_cloud_key: str | None
    source: SnapshotSource = SnapshotSource.photos


def run(job_id: str) -> str:
    return run_job(job_id, _compute, _persist)


def _load(ctx: JobContext) -> SnapshotInputs:
    snapshot_id = ctx.job.snapshot_id
    if snapshot_id is None:
        raise ValueError(f"job {ctx.job.id} has no snapshot")
    with transaction() as session:
        snap = snapshots.get(session, snapshot_id)
        env = environments.get(session, snap.environment_id)
        snap.state = SnapshotState.processing
        previous = snapshots.latest_reconstructed_before(session, snap)
        return SnapshotInputs(
            snapshot_id=snap.id,
            environment_id=env.id,
            prefix=snap.storage_prefix,
            classes=list(env.classes),
            reference=env.reference,
            options=dict(env.options.get("reconstruct", {})),
            previous_cloud_key=previous.pointcloud_key if previous else None,
            source=SnapshotSource(snap.source),
        )


def _compute(ctx: JobContext) -> tuple[SnapshotInputs, ReconstructionResult]:
    inputs = _load(ctx)
    if inputs.source == SnapshotSource.scan:  # a laser scan: read, not reconstructed
        return inputs, scan_snapshot.compute(ctx, inputs.prefix, inputs.reference, inputs.options)
    progress = weighted(ctx.progress, STAGE_WEIGHTS)
    progress("ingest", 0.0)
    records = ingest.read_capture(ctx.storage, inputs.prefix, inputs.classes, ctx.settings)
    with transaction() as session:
        ingest.record_images(session, inputs.snapshot_id, records)
    progress("ingest", 1.0)
    cameras_path = ctx.storage.path(f"{inputs.prefix}/cameras.json")
    options = dict(inputs.options)
    preset = str(options.pop("preset", ctx.job.preset or "default"))
    result = reconstruct(
        images_dir=ctx.storage.path(f"{inputs.prefix}/images"),
        work_dir=ctx.work_dir / "reconstruct",
        options=options_from_preset(preset, **options),
        cameras=load_cameras(cameras_path) if cameras_path.exists() else None,
        reference=inputs.reference,
        reference_cloud=(
            ctx.storage.path(inputs.previous_cloud_key) if inputs.previous_cloud_key else None
        ),
        progress=progress,
    )
    return inputs, result


def _persist(
    session: Session, ctx: JobContext, outcome: tuple[SnapshotInputs, ReconstructionResult]
) -> None:
    inputs, result = outcome
    out = f"{inputs.prefix}/reconstruction"
    ctx.storage.delete_prefix(out)
    for name, path in (("cloud.ply", result.cloud_path), ("cameras.json", result.cameras_path)):
        ctx.storage.move_in(Path(path), f"{out}/{name}")
    snap = snapshots.get(session, inputs.snapshot_id)
    snap.state = SnapshotState.reconstructed
    snap.quality = result.quality
    snap.pointcloud_key = f"{out}/cloud.ply"
    snap.cameras_key = f"{out}/cameras.json"
    snap.reconstructed_at = utcnow()
    session.flush()
    events.record(
        session,
        EventType.snapshot_reconstructed,
        environment_id=snap.environment_id,
        subject=f"snapshots/{snap.id}",
        data={
            "snapshot": snap.id,
            "environment": snap.environment_id,
            "seq": snap.seq,
            "quality": snap.quality,
            "links": {"pointcloud": f"/v1/snapshots/{snap.id}/pointcloud"},
        },
    )
    # the automatic comparison starts when every earlier snapshot is settled (seq order)
    twin.advance(session, snap.environment_id)
