"""The twin as it stands or as it stood at a snapshot, as rows (the JSON state) or as a
binary glTF scene with every instance's library model (:mod:`.gltf`).

A library model is read from the uploaded file when it is a PLY (mesh or cloud, scaled from
its units to metres); for the other formats (.obj .stl .off .glb .pcd) from the sampled
surface cloud its preparation job stored (``<artifacts>/model.ply``, metres), drawn as
points. An instance whose model cannot be had is still a node (its pose, no mesh), with
the reason in its extras; an instance whose pose is unknown is not drawn and is listed in
the root node's ``extras.undrawn``.
"""

from __future__ import annotations

import importlib.metadata
import logging
from dataclasses import dataclass
from datetime import datetime
from pathlib import PurePosixPath
from typing import Any

import numpy as np
from numpy.typing import NDArray
from sqlalchemy import select
from sqlalchemy.orm import Session

from app.core import objects, twin
from app.core.enums import SnapshotState, TwinUpdate
from app.core.errors import Conflict, NotFound
from app.core.export.gltf import ModelGeometry, ModelGeometryError, SceneNode, write_glb
from app.core.export.ply import PlyError, read_model
from app.core.models import Change, Environment, LibraryObject, Snapshot, TwinInstance
from app.core.storage import Storage

log = logging.getLogger(__name__)

FRAME_NOTE = (
    "twindelta environment frame: metres, +z up; the root node's matrix turns it into "
    "glTF's +y up (x -> x, y -> -z, z -> y)"
)


def generator() -> str:
    """``twindelta <version>``: the glTF asset generator and the LAS generating software."""
    try:
        return f"twindelta {importlib.metadata.version('twindelta')}"
    except importlib.metadata.PackageNotFoundError:
        return "twindelta"


@dataclass(frozen=True)
class InstanceState:
    """One instance as the state shows it: ``pose`` env_from_object (4×4, metres) or None
    when never estimated; ``since_snapshot`` the snapshot that gave it that pose (None: a
    seed or correction made before the twin reflected any snapshot); ``external_id`` the
    twin platform's id of it, when it has one."""

    instance_id: str
    object_name: str
    object_id: str | None
    pose: list[list[float]] | None
    pose_quality: dict[str, Any] | None
    since_snapshot: str | None
    created_snapshot: str | None
    created_at: datetime
    external_id: str | None = None


@dataclass(frozen=True)
class TwinView:
    """The instances of ``environment_id`` as of snapshot ``snapshot_id`` (number ``seq``);
    ``at_snapshot`` says whether a past snapshot was asked for."""

    environment_id: str
    snapshot_id: str | None
    seq: int
    at_snapshot: bool
    instances: list[InstanceState]


def view(session: Session, env: Environment, snapshot_id: str | None = None) -> TwinView:
    """The twin as it stands, or as it stood once snapshot ``snapshot_id`` was taken into
    account. NotFound (404) for a snapshot that is not one of this environment's (or was
    deleted); Conflict (409 ``SnapshotNotApplied``) for one the twin has not reflected: not
    reached yet, or skipped because it failed."""
    if snapshot_id is None:
        rows = [_current(i) for i in twin.current(session, env.id)]
        return TwinView(env.id, env.twin_snapshot_id, env.twin_seq or 0, False, rows)
    snap = session.get(Snapshot, snapshot_id)
    if snap is None or snap.environment_id != env.id or snap.state == SnapshotState.deleted:
        raise NotFound(f"snapshot {snapshot_id} not found in environment {env.id}")
    if snap.twin_update not in (TwinUpdate.baseline, TwinUpdate.applied):
        why = (
            "the twin has not reached it yet"
            if snap.twin_update is None
            else f"the twin skipped it (state {snap.state})"
        )
        raise Conflict(
            f"snapshot {snapshot_id} (seq {snap.seq}) is not reflected by the twin: {why}; "
            "ask for a snapshot whose twin_update is baseline or applied",
            code="SnapshotNotApplied",
        )
    rows = [
        InstanceState(
            instance_id=instance.id,
            object_name=instance.object_name,
            object_id=instance.object_id,
            pose=record.pose,
            pose_quality=_pose_quality(session, instance.id, record.comparison_id),
            since_snapshot=record.snapshot_id,
            created_snapshot=instance.created_snapshot_id,
            created_at=instance.created_at,
            external_id=instance.external_id,
        )
        for instance, record in twin.state_at(session, env.id, snap.seq)
    ]
    return TwinView(env.id, snap.id, snap.seq, True, rows)


def _current(i: TwinInstance) -> InstanceState:
    return InstanceState(
        instance_id=i.id,
        object_name=i.object_name,
        object_id=i.object_id,
        pose=i.pose,
        pose_quality=i.pose_quality,
        since_snapshot=i.since_snapshot_id,
        created_snapshot=i.created_snapshot_id,
        created_at=i.created_at,
        external_id=i.external_id,
    )


def _pose_quality(
    session: Session, instance_id: str, comparison_id: str | None
) -> dict[str, Any] | None:
    """The pose quality the change that set an instance's pose reported (None when that
    comparison is gone or had none)."""
    if comparison_id is None:
        return None
    quality = session.scalar(
        select(Change.pose_quality)
        .where(Change.comparison_id == comparison_id, Change.instance_id == instance_id)
        .limit(1)
    )
    return dict(quality) if isinstance(quality, dict) else None


def glb(session: Session, storage: Storage, twin_view: TwinView) -> bytes:
    """The ``.glb`` of ``twin_view`` (see the module docstring and :mod:`.gltf`)."""
    models: dict[str, ModelGeometry] = {}
    missing: dict[str, str] = {}  # library object id → why its model cannot be had
    nodes: list[SceneNode] = []
    undrawn: list[dict[str, Any]] = []
    for row in twin_view.instances:
        extras: dict[str, Any] = {
            "instance_id": row.instance_id,
            "external_id": row.external_id,
            "class": row.object_name,
            "object_id": row.object_id,
            "pose_quality": row.pose_quality,
            "since_snapshot": row.since_snapshot,
            "created_snapshot": row.created_snapshot,
        }
        pose, problem = _pose_matrix(row.pose)
        if pose is None:
            undrawn.append({**extras, "reason": problem})
            continue
        obj = _library_object(session, row)
        key = obj.id if obj is not None else None
        if obj is not None and obj.id not in models and obj.id not in missing:
            try:
                models[obj.id] = load_model(storage, obj)
            except (PlyError, ModelGeometryError, OSError) as exc:
                log.warning("model of library object %s not exported: %s", obj.id, exc)
                missing[obj.id] = f"the model could not be read: {exc}"
        if key is None or key in missing:
            extras["model_missing"] = missing.get(key or "", "no library object of this class")
            key = None
        name = f"{row.object_name}/{row.external_id or row.instance_id}"
        nodes.append(SceneNode(name, pose, key, extras))
    root = {
        "environment": twin_view.environment_id,
        "snapshot": twin_view.snapshot_id,
        "seq": twin_view.seq,
        "frame": FRAME_NOTE,
        "undrawn": undrawn,
    }
    return write_glb(nodes, models, root, generator())


def _pose_matrix(
    pose: list[list[float]] | None,
) -> tuple[NDArray[np.float64] | None, str | None]:
    """The 4×4 pose as an array, or None and why it cannot be drawn (unknown, or not a
    finite rigid transform, which a glTF node matrix must be)."""
    if pose is None:
        return None, "pose unknown"
    matrix = np.asarray(pose, dtype=np.float64)
    if matrix.shape != (4, 4) or not np.isfinite(matrix).all():
        return None, "pose is not a finite 4x4 matrix"
    rotation = matrix[:3, :3]
    rigid = np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-5)
    if not rigid or np.linalg.det(rotation) < 0 or not np.allclose(matrix[3], [0, 0, 0, 1]):
        return None, "pose is not a rigid transform"
    return matrix, None


def _library_object(session: Session, row: InstanceState) -> LibraryObject | None:
    """The instance's library object (kept when soft-deleted), else the live one of its
    class name."""
    if row.object_id is not None:
        obj = session.get(LibraryObject, row.object_id)
        if obj is not None:
            return obj
    return objects.by_names(session, [row.object_name]).get(row.object_name)


def load_model(storage: Storage, obj: LibraryObject) -> ModelGeometry:
    """The library object's model in metres (module docstring). PlyError when the file
    cannot be read; OSError (FileNotFoundError) when no readable model is stored."""
    if PurePosixPath(obj.file_key).suffix.lower() == ".ply":
        model = read_model(storage.local_file(obj.file_key))
        scale = objects.UNITS.get(obj.units, 1.0)
        return ModelGeometry(
            positions=model.positions * scale,
            normals=model.normals,
            colors=model.colors,
            triangles=model.triangles,
        )
    if obj.artifacts_key is None:
        raise FileNotFoundError(f"object {obj.id} is not prepared yet ({obj.state})")
    cloud = read_model(storage.local_file(f"{obj.artifacts_key}/model.ply"))
    return ModelGeometry(positions=cloud.positions, normals=cloud.normals, colors=cloud.colors)
