"""The twin's state: instances of library objects in an environment, with pose history."""

from __future__ import annotations

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.core.errors import NotFound
from app.core.models import InstancePose, TwinInstance


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
