"""The snapshot job: re-read the upload (image sizes, detections) → reconstruct the cloud
in the environment frame → take its inventory (every library object it shows, posed:
workers.pipeline.inventory) → publish the cloud and cameras under this attempt's folder
(``<prefix>/reconstruction/<job id>-<attempt>/``, before the transaction: workers.runner
.publish) → record quality, keys and inventory → move the twin's chain on
(app.core.twin.advance: the first snapshot fills the twin from its inventory; later ones
wait for the automatic comparison with the newest earlier reconstructed snapshot, once
every earlier snapshot is settled)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from sqlalchemy.orm import Session

from app.core import environments, events, ingest, inventory, objects, snapshots, twin
from app.core.db import transaction
from app.core.enums import EventType, ObjectState, SnapshotSource, SnapshotState
from app.core.models import utcnow
from workers import scan_snapshot
from workers.pipeline.compare.data import CaptureData
from workers.pipeline.compare.files import cameras_from_file, load_cloud, read_cameras_file
from workers.pipeline.errors import Cancelled, PipelineError
from workers.pipeline.inventory import inventory_options_from_json, take_inventory
from workers.pipeline.model import load_prepared
from workers.pipeline.reconstruct.cameras import load_cameras
from workers.pipeline.reconstruct.options import options_from_preset
from workers.pipeline.reconstruct.stage import ReconstructionResult, reconstruct
from workers.progress import weighted
from workers.runner import JobContext, Published, drop_stale, publish, run_job, unpublish

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
    "inventory": 10,
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
    # class → (diameter m, artifacts key) of the library objects ready to pose
    models: dict[str, tuple[float, str]] | None = None
    inventory_options: dict[str, Any] | None = None


@dataclass(frozen=True)
class Inventory:
    """The inventory stage's ``objects`` JSON and its summary (the options it ran with,
    supports, stats, rejected segments, or the error that stopped it)."""

    objects: list[dict[str, Any]]
    summary: dict[str, Any]


@dataclass(frozen=True)
class Outcome:
    """What the compute phase made: the reconstruction (or the scan's cloud), the inventory
    (None for a scan) and where its files were published."""

    inputs: SnapshotInputs
    result: ReconstructionResult
    inventory: Inventory | None
    published: Published


def run(job_id: str) -> str:
    return run_job(job_id, _compute, _persist, unpublish)


def _load(ctx: JobContext) -> SnapshotInputs:
    snapshot_id = ctx.job.snapshot_id
    if snapshot_id is None:
        raise ValueError(f"job {ctx.job.id} has no snapshot")
    with transaction() as session:
        snap = snapshots.get(session, snapshot_id)
        env = environments.get(session, snap.environment_id)
        snap.state = SnapshotState.processing
        previous = snapshots.latest_reconstructed_before(session, snap)
        library = objects.by_names(session, list(env.classes))
        return SnapshotInputs(
            snapshot_id=snap.id,
            environment_id=env.id,
            prefix=snap.storage_prefix,
            classes=list(env.classes),
            reference=env.reference,
            options=dict(env.options.get("reconstruct", {})),
            previous_cloud_key=previous.pointcloud_key if previous else None,
            source=SnapshotSource(snap.source),
            models={
                name: (float(obj.diameter_m), obj.artifacts_key)
                for name, obj in library.items()
                if obj.state == ObjectState.ready and obj.diameter_m and obj.artifacts_key
            },
            inventory_options=dict(env.options.get("inventory", {})),
        )


def _compute(ctx: JobContext) -> Outcome:
    inputs = _load(ctx)
    if inputs.source == SnapshotSource.scan:  # a laser scan: read, not reconstructed
        # no photos, so no detector boxes to identify objects by: no inventory
        result = scan_snapshot.compute(ctx, inputs.prefix, inputs.reference, inputs.options)
        found = None
    else:
        result, found = _reconstruct(ctx, inputs)
    files = {"cloud.ply": Path(result.cloud_path), "cameras.json": Path(result.cameras_path)}
    return Outcome(inputs, result, found, publish(ctx, f"{inputs.prefix}/reconstruction", files))


def _reconstruct(ctx: JobContext, inputs: SnapshotInputs) -> tuple[ReconstructionResult, Inventory]:
    """Ingest (the photos fetched and listed once), reconstruction and inventory."""
    progress = weighted(ctx.progress, STAGE_WEIGHTS)
    progress("ingest", 0.0)
    images_dir = ctx.storage.local_dir(f"{inputs.prefix}/images")
    records = ingest.read_capture(
        ctx.storage, inputs.prefix, inputs.classes, ctx.settings, images_dir=images_dir
    )
    with transaction() as session:
        ingest.record_images(session, inputs.snapshot_id, records)
    progress("ingest", 1.0)
    try:
        cameras_path: Path | None = ctx.storage.local_file(f"{inputs.prefix}/cameras.json")
    except FileNotFoundError:  # an upload without cameras.json: SfM self-calibrates
        cameras_path = None
    options = dict(inputs.options)
    preset = str(options.pop("preset", ctx.job.preset or "default"))
    result = reconstruct(
        images_dir=images_dir,
        work_dir=ctx.work_dir / "reconstruct",
        options=options_from_preset(preset, **options),
        cameras=load_cameras(cameras_path) if cameras_path is not None else None,
        reference=inputs.reference,
        reference_cloud=(
            ctx.storage.local_file(inputs.previous_cloud_key) if inputs.previous_cloud_key else None
        ),
        progress=progress,
    )
    return result, _inventory(ctx, inputs, result, records, images_dir, progress)


def _inventory(
    ctx: JobContext,
    inputs: SnapshotInputs,
    result: ReconstructionResult,
    records: list[ingest.ImageRecord],
    images_dir: Path,
    progress: Any,
) -> Inventory:
    """Every library object the reconstruction shows (workers.pipeline.inventory; empty
    while no library object of the classes is ready to pose). A pipeline failure here
    leaves the reconstruction good: the summary carries the error and the inventory is
    empty; bad options fail the job (InputError). The summary keeps the options as the
    environment gives them (``{"preset": name, **overrides}``), as a comparison keeps its."""
    given = dict(inputs.inventory_options or {})
    given = {"preset": str(given.pop("preset", "default")), **given}
    options = inventory_options_from_json(given)
    models = inputs.models or {}
    points, colors = load_cloud(result.cloud_path)
    capture = CaptureData(
        points_env=points,
        cameras=cameras_from_file(read_cameras_file(result.cameras_path), "cameras.json"),
        detections={
            r.name: np.asarray(
                [
                    [d["class_id"], d["cx"], d["cy"], d["w"], d["h"], d.get("confidence") or 1.0]
                    for d in r.detections
                ],
                dtype=np.float64,
            ).reshape(-1, 6)
            for r in records
        },
        colors=colors,
        photos={r.name: images_dir / r.name for r in records if (images_dir / r.name).is_file()},
    )
    try:
        found = take_inventory(
            capture,
            inputs.classes,
            {name: diameter for name, (diameter, _) in models.items()},
            lambda name: load_prepared(ctx.storage.local_dir(models[name][1])),
            options,
            progress,
        )
    except Cancelled:
        raise
    except PipelineError as exc:
        return Inventory([], {"options": given, "error": {"code": exc.code, "detail": exc.detail}})
    data = found.to_json()
    return Inventory(
        data["objects"],
        {"options": given, **{k: data[k] for k in ("supports", "stats", "rejected")}},
    )


def _persist(session: Session, ctx: JobContext, outcome: Outcome) -> None:
    """Record the published files (no bucket call here); other attempts' folders go after
    the commit."""
    inputs, result, found = outcome.inputs, outcome.result, outcome.inventory
    published = outcome.published
    drop_stale(session, ctx, published)
    snap = snapshots.get(session, inputs.snapshot_id)
    snap.state = SnapshotState.reconstructed
    snap.quality = result.quality
    snap.pointcloud_key = published.key("cloud.ply")
    snap.cameras_key = published.key("cameras.json")
    snap.reconstructed_at = utcnow()
    if found is not None:
        inventory.record(session, snap, found.objects, found.summary)
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
