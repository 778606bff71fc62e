"""The twin's history records as the events about them read them."""

from __future__ import annotations

from collections.abc import Iterable

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.core.enums import ChangeType
from app.core.models import Comparison, InstancePose, TwinInstance


def open_instances(session: Session, environment_id: str) -> list[TwinInstance]:
    """The environment's open instances (not removed), oldest first."""
    return list(
        session.scalars(
            select(TwinInstance)
            .where(
                TwinInstance.environment_id == environment_id,
                TwinInstance.closed_snapshot_id.is_(None),
            )
            .order_by(TwinInstance.created_at, TwinInstance.id)
        )
    )


def changed_instances(
    session: Session, snapshot_id: str, comparison_id: str
) -> list[tuple[InstancePose, TwinInstance]]:
    """Each instance a comparison's changes touched when the twin applied them at
    ``snapshot_id``, with its last record of that comparison (an instance named twice: the
    last wins), in the order the twin applied them."""
    rows = session.execute(
        select(InstancePose, TwinInstance)
        .join(TwinInstance, TwinInstance.id == InstancePose.instance_id)
        .where(
            InstancePose.snapshot_id == snapshot_id,
            InstancePose.comparison_id == comparison_id,
        )
        .order_by(InstancePose.created_at, InstancePose.id)
    ).all()
    latest: dict[str, tuple[InstancePose, TwinInstance]] = {}
    for record, instance in rows:
        latest.pop(instance.id, None)
        latest[instance.id] = (record, instance)
    return list(latest.values())


def removed_instances(session: Session, snapshot_id: str, comparison_id: str) -> list[TwinInstance]:
    """The instances a comparison's ``removed`` changes closed at ``snapshot_id`` (and that
    stay closed), in the order the twin closed them."""
    return list(
        session.scalars(
            select(TwinInstance)
            .join(InstancePose, InstancePose.instance_id == TwinInstance.id)
            .where(
                InstancePose.snapshot_id == snapshot_id,
                InstancePose.comparison_id == comparison_id,
                InstancePose.change_type == ChangeType.removed,
                TwinInstance.closed_snapshot_id == snapshot_id,
            )
            .order_by(InstancePose.created_at, InstancePose.id)
        )
    )


def inventoried_instances(
    session: Session, snapshot_id: str
) -> list[tuple[InstancePose, TwinInstance]]:
    """Each instance a snapshot's inventory filled the twin with (its baseline: records
    made at ``snapshot_id`` by no comparison), in the order they were made."""
    rows = session.execute(
        select(InstancePose, TwinInstance)
        .join(TwinInstance, TwinInstance.id == InstancePose.instance_id)
        .where(InstancePose.snapshot_id == snapshot_id, InstancePose.comparison_id.is_(None))
        .order_by(InstancePose.created_at, InstancePose.id)
    ).all()
    return [(record, instance) for record, instance in rows]


def external_ids(session: Session, instance_ids: Iterable[str | None]) -> dict[str, str]:
    """instance id → the twin platform's id, for those of ``instance_ids`` that have one
    (as they are now: a correction shows in every comparison that names the instance)."""
    wanted = sorted({i for i in instance_ids if i})
    if not wanted:
        return {}
    rows = session.execute(
        select(TwinInstance.id, TwinInstance.external_id).where(
            TwinInstance.id.in_(wanted), TwinInstance.external_id.is_not(None)
        )
    ).all()
    return {str(iid): str(ext) for iid, ext in rows}


def comparison_external_ids(session: Session, comparisons: Iterable[Comparison]) -> dict[str, str]:
    """:func:`external_ids` of every instance the comparisons' changes name."""
    return external_ids(
        session,
        (
            i
            for c in comparisons
            for ch in c.changes
            for i in (ch.instance_id, ch.replaced_instance_id)
        ),
    )
