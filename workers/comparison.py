"""The comparison job: change detection and identification between two snapshots, a pose
for every identified object that appeared, a re-projection check of each pose, the change
clusters' points published under this attempt's folder (workers.runner.publish), then the
result, the ``comparison.completed`` event and, for an automatic comparison, the twin's
update (app.core.twin.advance, in seq order) in one transaction."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d
from sqlalchemy import select
from sqlalchemy.orm import Session

from app.core import (
    change_clusters,
    comparisons,
    environments,
    events,
    jobs,
    objects,
    snapshots,
    twin,
    twin_records,
)
from app.core.db import transaction
from app.core.enums import ComparisonState, EventType, ObjectState
from app.core.models import Change, InstancePose, SnapshotImage, utcnow
from app.core.models import TwinInstance as Instance
from app.core.storage import Storage
from workers.pipeline.compare.data import CaptureData, TwinInstance
from workers.pipeline.compare.files import cameras_from_file, read_cameras_file
from workers.pipeline.compare.options import options_from_json
from workers.pipeline.compare.results import CompareResult
from workers.pipeline.compare.stage import compare_snapshots
from workers.pipeline.errors import PipelineError
from workers.pipeline.model import load_prepared
from workers.pipeline.pose.posing import pose_changes
from workers.progress import weighted
from workers.runner import JobContext, Published, drop_stale, publish, run_job, unpublish

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CaptureFiles:
    snapshot_id: str
    cloud_key: str
    cameras_key: str
    alignment_residual_m: float
    detections: dict[str, list[list[float]]]
    photo_keys: dict[str, str]  # image name → stored photo


@dataclass(frozen=True)
class ComparisonInputs:
    comparison_id: str
    environment_id: str
    before: CaptureFiles
    after: CaptureFiles
    classes: list[str]
    options: dict[str, Any]
    twin: list[TwinInstance]
    models: dict[str, tuple[str, float, str]]  # class → (object id, diameter m, artifacts key)
    folder: str  # the comparison's folder (app.core.change_clusters.comparison_folder)


@dataclass
class ComparisonOutcome:
    inputs: ComparisonInputs
    result: CompareResult
    published: Published  # the change clusters' points
    changes: list[dict[str, Any]] = field(default_factory=list)


def run(job_id: str) -> str:
    return run_job(job_id, _compute, _persist, unpublish)


def _capture(session: Session, snapshot_id: str) -> CaptureFiles:
    snap = snapshots.get(session, snapshot_id)
    if not snap.pointcloud_key or not snap.cameras_key:
        raise PipelineError(f"snapshot {snap.id} has no reconstruction", code="NotReconstructed")
    images = session.scalars(
        select(SnapshotImage).where(SnapshotImage.snapshot_id == snapshot_id)
    ).all()
    return CaptureFiles(
        snapshot_id=snap.id,
        cloud_key=snap.pointcloud_key,
        cameras_key=snap.cameras_key,
        alignment_residual_m=float(snap.quality.get("alignment_residual_m") or 0.0),
        detections={
            image.name: [
                [d["class_id"], d["cx"], d["cy"], d["w"], d["h"], d.get("confidence") or 1.0]
                for d in image.detections
            ]
            for image in images
        },
        photo_keys={image.name: image.file_key for image in images},
    )


def _load(ctx: JobContext) -> ComparisonInputs:
    comparison_id = ctx.job.comparison_id
    if comparison_id is None:
        raise ValueError(f"job {ctx.job.id} has no comparison")
    with transaction() as session:
        comparison = comparisons.get(session, comparison_id)
        comparison.state = ComparisonState.running
        env = environments.get(session, comparison.environment_id)
        before_seq = snapshots.get(session, comparison.before_id).seq
        state = twin.state_at(session, env.id, before_seq)
        library = objects.by_names(session, list(env.classes))
        after_prefix = snapshots.get(session, comparison.after_id).storage_prefix
        return ComparisonInputs(
            comparison_id=comparison.id,
            environment_id=env.id,
            folder=change_clusters.comparison_folder(after_prefix, comparison.id),
            before=_capture(session, comparison.before_id),
            after=_capture(session, comparison.after_id),
            classes=list(env.classes),
            options=dict(comparison.options),
            twin=compare_twin(state),
            models={
                name: (obj.id, float(obj.diameter_m), obj.artifacts_key)
                for name, obj in library.items()
                if obj.state == ObjectState.ready and obj.diameter_m and obj.artifacts_key
            },
        )


def compare_twin(state: Sequence[tuple[Instance, InstancePose]]) -> list[TwinInstance]:
    """The twin as the compare stage takes it (``state``: :func:`app.core.twin.state_at`):
    each instance at its latest pose, or at its centroid where it has none; an instance with
    neither is left out."""
    return [
        TwinInstance(
            instance_id=instance.id,
            object_name=instance.object_name,
            env_from_object=np.asarray(
                record.pose if record.pose is not None else _at(record.centroid_env)
            ),
            centroid_env=(np.asarray(record.centroid_env) if record.centroid_env else None),
        )
        for instance, record in state
        if record.pose is not None or record.centroid_env is not None
    ]


def _at(centroid: list[float] | None) -> list[list[float]]:
    pose = np.eye(4)
    pose[:3, 3] = centroid or [0.0, 0.0, 0.0]
    return [[float(v) for v in row] for row in pose]


def _capture_data(ctx: JobContext, files: CaptureFiles) -> CaptureData:
    cloud = o3d.io.read_point_cloud(ctx.storage.local_file(files.cloud_key))
    cameras = read_cameras_file(ctx.storage.local_file(files.cameras_key))
    return CaptureData(
        points_env=np.asarray(cloud.points, dtype=np.float64),
        cameras=cameras_from_file(cameras, files.cameras_key),
        detections={
            name: np.asarray(rows, dtype=np.float64).reshape(-1, 6)
            for name, rows in files.detections.items()
        },
        colors=np.asarray(cloud.colors, dtype=np.float64) if cloud.has_colors() else None,
        alignment_residual_m=files.alignment_residual_m,
        photos=local_photos(ctx.storage, files.photo_keys),
    )


def local_photos(storage: Storage, keys: dict[str, str]) -> dict[str, Path]:
    """Local files of a capture's stored photos; one that cannot be fetched is left out (the
    seen checks then go by depth alone for that camera)."""
    out = {}
    for name, key in keys.items():
        try:
            out[name] = storage.local_file(key)
        except FileNotFoundError:
            log.warning("photo %s (%s) is not stored: its seen checks go by depth", name, key)
    return out


def _compute(ctx: JobContext) -> ComparisonOutcome:
    inputs = _load(ctx)
    progress = weighted(ctx.progress, {"load": 1, "compare": 6, "pose": 3})
    progress("load", 0.0)
    before = _capture_data(ctx, inputs.before)
    after = _capture_data(ctx, inputs.after)
    options = dict(inputs.options)
    preset = str(options.pop("preset", "default"))
    pose_options = options.pop("pose", {})
    compare_options = options_from_json(preset, options)
    result = compare_snapshots(
        before,
        after,
        inputs.twin,
        inputs.classes,
        {name: diameter for name, (_, diameter, _) in inputs.models.items()},
        compare_options,
        progress,
    )
    changes = list(
        pose_changes(
            result,
            after,
            inputs.classes,
            inputs.models,
            lambda name: load_prepared(ctx.storage.local_dir(inputs.models[name][2])),
            compare_options,
            pose_options,
            progress,
        )
    )
    npz = ctx.work_dir / change_clusters.FILE
    npz.write_bytes(clusters_npz(result))
    published = publish(ctx, inputs.folder, {change_clusters.FILE: npz})
    return ComparisonOutcome(inputs=inputs, result=result, published=published, changes=changes)


def clusters_npz(result: CompareResult) -> bytes:
    """The ``clusters.npz`` of the change clusters' points for the console (at most 20 000
    a cluster; app.core.change_clusters)."""
    change_of: dict[int, str] = {}
    for change in result.changes:
        for cluster in (change.cluster, change.previous_cluster):
            if cluster is not None:
                change_of.setdefault(cluster.id, change.id)
    return change_clusters.to_npz(
        [
            change_clusters.StoredCluster(
                id=c.id,
                side=c.side,
                change_id=change_of.get(c.id),
                n_points=c.n_points,
                points_env=c.points_env,
            )
            for c in result.clusters
        ],
    )


def _persist(session: Session, ctx: JobContext, outcome: ComparisonOutcome) -> None:
    inputs, result = outcome.inputs, outcome.result
    drop_stale(session, ctx, outcome.published)
    comparison = comparisons.get(session, inputs.comparison_id)
    data = result.to_json()
    comparison.state = ComparisonState.succeeded
    comparison.distances = {
        side: {**stats, "histogram": _histogram(raw, float(stats["threshold"]))}
        for side, stats, raw in (
            ("added", data["distances"]["added"], result.added_distances_m),
            ("removed", data["distances"]["removed"], result.removed_distances_m),
        )
    }
    boxes = {c.id: {name: box.tolist() for name, box in c.boxes.items()} for c in result.clusters}
    comparison.clusters = [{**row, "boxes": boxes.get(row["id"], {})} for row in data["clusters"]]
    comparison.options = {**comparison.options, "resolved": data["options"]}
    comparison.completed_at = utcnow()
    object_ids = {name: object_id for name, (object_id, _, _) in inputs.models.items()}
    for position, change in enumerate(outcome.changes):
        comparison.changes.append(
            Change(
                id=change["id"],
                position=position,
                type=change["type"],
                object_name=change.get("object"),
                object_id=object_ids.get(str(change.get("object"))),
                instance_id=change.get("instance_id"),
                pose=change.get("pose"),
                previous_pose=change.get("previous_pose"),
                replaced_object=change.get("replaced_object"),
                replaced_instance_id=change.get("replaced_instance_id"),
                centroid_env=change.get("centroid_env"),
                identification=change.get("identification"),
                cluster=change["cluster"],
                pose_quality=change.get("pose_quality"),
            )
        )
    jobs.get(session, ctx.job.id).result = {"stats": data.get("stats", {})}
    session.flush()
    platform_ids = twin_records.external_ids(
        session, (change.get("instance_id") for change in outcome.changes)
    )
    events.record(
        session,
        EventType.comparison_completed,
        environment_id=inputs.environment_id,
        subject=f"comparisons/{comparison.id}",
        data={
            "comparison": comparison.id,
            "environment": inputs.environment_id,
            "before": comparison.before_id,
            "after": comparison.after_id,
            "changes": [
                {
                    **{
                        key: change.get(key)
                        for key in (
                            "id",
                            "type",
                            "object",
                            "instance_id",
                            "pose",
                            "previous_pose",
                            "replaced_object",
                            "pose_quality",
                        )
                    },
                    "external_id": platform_ids.get(str(change.get("instance_id"))),
                }
                for change in outcome.changes
            ],
            "links": {"comparison": f"/v1/comparisons/{comparison.id}"},
        },
    )
    if comparison.automatic:
        # applied to the twin when its turn comes (every earlier snapshot applied or
        # skipped): now, or by whichever later transaction makes it due
        twin.advance(session, inputs.environment_id)


def _histogram(distances_m: Any, threshold_m: float, bins: int = 60) -> dict[str, Any]:
    """Counts of C2C distances in ``bins`` equal bins up to max(2 × threshold, p99), metres
    (the thesis's distribution figures)."""
    d = np.asarray(distances_m, dtype=np.float64)
    d = d[np.isfinite(d)]
    top = max(2.0 * threshold_m, float(np.percentile(d, 99)) if len(d) else 0.0, 1e-6)
    counts, edges = np.histogram(np.clip(d, 0.0, top), bins=bins, range=(0.0, top))
    return {"bin_width_m": float(edges[1] - edges[0]), "counts": counts.tolist()}
