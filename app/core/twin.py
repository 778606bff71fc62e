"""The twin's state: instances of library objects in an environment, with pose history."""

from __future__ import annotations

import logging
from typing import Any

from sqlalchemy import or_, select
from sqlalchemy.orm import Session, aliased

from app.core.enums import ChangeType
from app.core.errors import NotFound
from app.core.models import InstancePose, Snapshot, TwinInstance, utcnow

log = logging.getLogger(__name__)


def current(session: Session, environment_id: str) -> list[TwinInstance]:
    """Open instances (not removed), oldest first."""
    return list(
        session.scalars(
            select(TwinInstance)
            .where(
                TwinInstance.environment_id == environment_id,
                TwinInstance.closed_snapshot_id.is_(None),
            )
            .order_by(TwinInstance.created_at)
        ).all()
    )


def history(
    session: Session, environment_id: str, instance_id: str
) -> tuple[TwinInstance, list[InstancePose]]:
    instance = session.get(TwinInstance, instance_id)
    if instance is None or instance.environment_id != environment_id:
        raise NotFound(f"instance {instance_id} not found in environment {environment_id}")
    poses = session.scalars(
        select(InstancePose)
        .where(InstancePose.instance_id == instance_id)
        .order_by(InstancePose.created_at)
    ).all()
    return instance, list(poses)


def state_at(
    session: Session, environment_id: str, seq: int
) -> list[tuple[TwinInstance, InstancePose]]:
    """The twin as it stood once snapshot number ``seq`` was applied: every instance open at
    that time with its latest history record then (pose None when never estimated)."""
    created = aliased(Snapshot)
    closed = aliased(Snapshot)
    instances = session.scalars(
        select(TwinInstance)
        .join(created, TwinInstance.created_snapshot_id == created.id)
        .outerjoin(closed, TwinInstance.closed_snapshot_id == closed.id)
        .where(
            TwinInstance.environment_id == environment_id,
            created.seq <= seq,
            or_(closed.id.is_(None), closed.seq > seq),
        )
        .order_by(TwinInstance.created_at)
    ).all()
    out: list[tuple[TwinInstance, InstancePose]] = []
    for instance in instances:
        record = session.scalar(
            select(InstancePose)
            .join(Snapshot, InstancePose.snapshot_id == Snapshot.id)
            .where(InstancePose.instance_id == instance.id, Snapshot.seq <= seq)
            .order_by(Snapshot.seq.desc(), InstancePose.created_at.desc())
            .limit(1)
        )
        if record is not None:
            out.append((instance, record))
    return out


def apply_changes(
    session: Session,
    environment_id: str,
    snapshot_id: str,
    comparison_id: str,
    changes: list[dict[str, Any]],
    object_ids: dict[str, str],
) -> None:
    """Write a comparison's changes into the twin: added creates an instance, removed closes
    it, moved appends a pose, swapped closes one and creates another; unidentified changes
    leave the twin alone. Every pose goes into the instance's history."""
    now = utcnow()

    def record(instance_id: str, change_type: str, change: dict[str, Any] | None) -> None:
        session.add(
            InstancePose(
                instance_id=instance_id,
                snapshot_id=snapshot_id,
                comparison_id=comparison_id,
                change_type=change_type,
                pose=change.get("pose") if change else None,
                centroid_env=change.get("centroid_env") if change else None,
            )
        )

    def close(instance_id: str | None, change_type: str) -> None:
        instance = session.get(TwinInstance, instance_id) if instance_id else None
        if instance is None or instance.closed_snapshot_id is not None:
            log.warning("change %s names no open instance %s", change_type, instance_id)
            return
        instance.closed_snapshot_id, instance.closed_at = snapshot_id, now
        record(instance.id, change_type, None)

    def create(change: dict[str, Any]) -> None:
        name = str(change["object"])
        session.add(
            TwinInstance(
                id=change["instance_id"],
                environment_id=environment_id,
                object_name=name,
                object_id=object_ids.get(name),
                pose=change.get("pose"),
                pose_quality=change.get("pose_quality"),
                centroid_env=change.get("centroid_env"),
                since_snapshot_id=snapshot_id,
                created_snapshot_id=snapshot_id,
            )
        )
        session.flush()
        record(change["instance_id"], str(change["type"]), change)

    for change in changes:
        kind = change["type"]
        if kind == ChangeType.added:
            create(change)
        elif kind == ChangeType.removed:
            close(change.get("instance_id"), ChangeType.removed)
        elif kind == ChangeType.moved:
            instance = session.get(TwinInstance, change.get("instance_id") or "")
            if instance is None or instance.closed_snapshot_id is not None:
                create({**change, "type": ChangeType.added})
                continue
            instance.pose, instance.pose_quality = change.get("pose"), change.get("pose_quality")
            instance.centroid_env = change.get("centroid_env")
            instance.since_snapshot_id = snapshot_id
            record(instance.id, ChangeType.moved, change)
        elif kind == ChangeType.swapped:
            close(change.get("replaced_instance_id"), ChangeType.swapped)
            create(change)
    session.flush()
