"""The inventory of each snapshot in the database, and what the twin makes of it.

The snapshot job stores what the inventory stage found (:func:`record`: one
:class:`~app.core.models.SnapshotObject` per library object, its summary on the snapshot).
When the twin reaches the snapshot (app.core.twin.advance):

- the **first** snapshot fills the twin (:func:`fill_baseline`): each object becomes an
  instance with a history record ``inventoried``, except where an instance seeded by the
  twin platform stands (same class, within :func:`match_reach_m`): that instance takes the
  inventory's pose (record ``inventoried``) and keeps its external id;
- a **later** snapshot, once its comparison's changes are applied, confirms the open
  instances it shows (:func:`confirm`): the object is linked to the instance (so
  ``last_seen_snapshot`` moves on); the pose is refreshed, with a record ``drifted``, only
  when the inventory's pose is further from the twin's than the pose estimate's noise
  (:data:`DRIFT_TRANSLATION_M`, :data:`DRIFT_ROTATION_DEG`), which also catches a slow
  drift no single comparison flagged, and may replace it (:func:`takes_inventory_pose`:
  verified, or both unverified estimates; where the comparison just posed the instance,
  only a verified pose replacing an unverified one); an instance the comparison
  ``removed`` that the inventory still shows where it stood (an object of its class within
  :func:`match_reach_m` that no open instance accounts for) is reopened, with a record
  ``restored``, so it keeps its id and external id; a posed object no instance accounts
  for is added (``inventoried``), as the first snapshot would have. An instance no object
  confirms keeps its state: not seen.

Never commits.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from app.core import objects
from app.core.enums import TwinEdit
from app.core.errors import Conflict
from app.core.models import (
    Environment,
    InstancePose,
    LibraryObject,
    Snapshot,
    SnapshotObject,
    TwinInstance,
)
from app.core.twin_records import open_instances, removed_instances

#: a verified inventory pose this far from the twin's (metres, degrees) is a real move, not
#: the pose estimate's noise: the inventory's pose targets (every verified pose within
#: 1 cm / 3°)
DRIFT_TRANSLATION_M = 0.01
DRIFT_ROTATION_DEG = 3.0
#: an instance and an object of its class are one when closer than this × its diameter ...
MATCH_DIAMETERS = 1.0
#: ... or this many metres, whichever is larger (the compare stage's instance_match_min)
MATCH_MIN_M = 0.25


def record(
    session: Session,
    snapshot: Snapshot,
    found: Sequence[dict[str, Any]],
    summary: dict[str, Any],
) -> list[SnapshotObject]:
    """Store the inventory stage's objects (its ``objects`` JSON) and ``summary`` on
    ``snapshot``, replacing an earlier inventory of it."""
    for old in session.scalars(
        select(SnapshotObject).where(SnapshotObject.snapshot_id == snapshot.id)
    ):
        session.delete(old)
    env = session.get(Environment, snapshot.environment_id)
    library = objects.by_names(session, list(env.classes) if env else [])
    rows = []
    for position, obj in enumerate(found):
        name = str(obj["object"])
        row = SnapshotObject(
            snapshot_id=snapshot.id,
            position=position,
            object_name=name,
            object_id=library[name].id if name in library else None,
            pose=obj.get("pose"),
            pose_quality=obj.get("pose_quality"),
            identification=dict(obj.get("identification") or {}),
            centroid_env=[float(v) for v in obj["centroid_env"]],
            support=obj.get("support"),
        )
        session.add(row)
        rows.append(row)
    snapshot.inventory = {**summary, "objects": len(rows)}
    session.flush()
    return rows


class NotInventoried(Conflict):
    code = "NotInventoried"


def require_inventory(snapshot: Snapshot) -> None:
    """NotInventoried (409) unless the snapshot's inventory was taken."""
    if snapshot.inventory is None:
        raise NotInventoried(
            f"snapshot {snapshot.id} has no inventory (state {snapshot.state}; a laser scan or "
            "a snapshot reconstructed before inventories has none)"
        )
    if "error" in snapshot.inventory:
        why = snapshot.inventory["error"].get("detail")
        raise NotInventoried(f"snapshot {snapshot.id} has no inventory: {why}")


def objects_of(session: Session, snapshot_id: str) -> list[SnapshotObject]:
    """The snapshot's inventory, in the stage's order."""
    return list(
        session.scalars(
            select(SnapshotObject)
            .where(SnapshotObject.snapshot_id == snapshot_id)
            .order_by(SnapshotObject.position)
        )
    )


def last_seen(session: Session, instance_ids: Iterable[str]) -> dict[str, str]:
    """instance id → the newest snapshot (by seq) whose inventory showed it."""
    wanted = sorted(set(instance_ids))
    if not wanted:
        return {}
    newest = (
        select(SnapshotObject.instance_id, func.max(Snapshot.seq).label("seq"))
        .join(Snapshot, Snapshot.id == SnapshotObject.snapshot_id)
        .where(SnapshotObject.instance_id.in_(wanted))
        .group_by(SnapshotObject.instance_id)
        .subquery()
    )
    rows = session.execute(
        select(newest.c.instance_id, Snapshot.id)
        .join(SnapshotObject, SnapshotObject.instance_id == newest.c.instance_id)
        .join(
            Snapshot,
            (Snapshot.id == SnapshotObject.snapshot_id) & (Snapshot.seq == newest.c.seq),
        )
    ).all()
    return {str(i): str(s) for i, s in rows}


def match_reach_m(diameter_m: float | None) -> float:
    """How far an instance and an object of its class may be apart and still be one."""
    return max(MATCH_DIAMETERS * float(diameter_m or 0.0), MATCH_MIN_M)


def _position(pose: Any, centroid: Any) -> np.ndarray | None:
    """Where an instance or object is: its centre when known (a symmetric object's model
    origin may lie off its axis, anywhere on a circle about it), else its pose's origin."""
    if centroid is not None:
        return np.asarray(centroid, dtype=np.float64)
    return None if pose is None else np.asarray(pose, dtype=np.float64)[:3, 3]


def _pairs(
    instances: Sequence[TwinInstance],
    found: Sequence[SnapshotObject],
    library: dict[str, LibraryObject],
) -> list[tuple[TwinInstance, SnapshotObject]]:
    """Instance–object pairs of one class within reach, nearest first, each used once
    (instance positions by pose else centroid; objects' by pose else centroid)."""
    candidates = []
    for i, instance in enumerate(instances):
        here = _position(instance.pose, instance.centroid_env)
        if here is None:
            continue
        for j, obj in enumerate(found):
            if obj.object_name != instance.object_name:
                continue
            there = _position(obj.pose, obj.centroid_env)
            if there is None:
                continue
            lib = library.get(obj.object_name)
            d = float(np.linalg.norm(here - there))
            if d <= match_reach_m(lib.diameter_m if lib else None):
                candidates.append((d, i, j))
    used_i: set[int] = set()
    used_j: set[int] = set()
    out = []
    for _d, i, j in sorted(candidates):
        if i in used_i or j in used_j:
            continue
        used_i.add(i)
        used_j.add(j)
        out.append((instances[i], found[j]))
    return out


def _note(
    session: Session,
    instance: TwinInstance,
    snapshot_id: str,
    comparison_id: str | None,
    kind: str,
    obj: SnapshotObject,
) -> None:
    """Give ``instance`` the object's pose and a history record ``kind``."""
    if obj.pose is not None:
        instance.pose, instance.pose_quality = obj.pose, obj.pose_quality
    instance.centroid_env = obj.centroid_env
    instance.since_snapshot_id = snapshot_id
    _record(session, instance.id, snapshot_id, comparison_id, kind, obj.pose, obj.centroid_env)


def _record(
    session: Session,
    instance_id: str,
    snapshot_id: str,
    comparison_id: str | None,
    kind: str,
    pose: Any,
    centroid_env: Any,
) -> None:
    session.add(
        InstancePose(
            instance_id=instance_id,
            snapshot_id=snapshot_id,
            comparison_id=comparison_id,
            change_type=kind,
            pose=pose,
            centroid_env=centroid_env,
        )
    )


def _create(
    session: Session,
    env: Environment,
    snapshot_id: str,
    comparison_id: str | None,
    obj: SnapshotObject,
) -> TwinInstance:
    instance = TwinInstance(
        environment_id=env.id,
        object_name=obj.object_name,
        object_id=obj.object_id,
        pose=obj.pose,
        pose_quality=obj.pose_quality,
        centroid_env=obj.centroid_env,
        since_snapshot_id=snapshot_id,
        created_snapshot_id=snapshot_id,
    )
    session.add(instance)
    session.flush()
    _note(session, instance, snapshot_id, comparison_id, TwinEdit.inventoried, obj)
    return instance


def fill_baseline(session: Session, env: Environment, head: Snapshot) -> list[TwinInstance]:
    """The first snapshot's inventory into the twin (see the module docstring); returns the
    instances it created or took over."""
    found = objects_of(session, head.id)
    if not found:
        return []
    library = objects.by_names(session, sorted({o.object_name for o in found}))
    seeded = open_instances(session, env.id)
    taken: list[TwinInstance] = []
    matched = _pairs(seeded, found, library)
    for instance, obj in matched:
        _note(session, instance, head.id, None, TwinEdit.inventoried, obj)
        obj.instance_id = instance.id
        taken.append(instance)
    paired = {id(obj) for _, obj in matched}
    for obj in found:
        if id(obj) not in paired:
            instance = _create(session, env, head.id, None, obj)
            obj.instance_id = instance.id
            taken.append(instance)
    session.flush()
    return taken


def _rotation_deg(a: Any, b: Any) -> float:
    ra, rb = np.asarray(a, dtype=np.float64)[:3, :3], np.asarray(b, dtype=np.float64)[:3, :3]
    cos = (float(np.trace(ra.T @ rb)) - 1.0) / 2.0
    return math.degrees(math.acos(max(-1.0, min(1.0, cos))))


def moved_beyond_noise(
    twin_pose: Any,
    inventory_pose: Any,
    twin_centre: Any = None,
    inventory_centre: Any = None,
    symmetric: bool = False,
) -> bool:
    """Whether an instance moved beyond the pose estimate's noise: its centre (else its
    pose's origin) by more than :data:`DRIFT_TRANSLATION_M`, or, unless the object is
    symmetric (any turn about its axis is the same object), its rotation by more than
    :data:`DRIFT_ROTATION_DEG`."""
    if twin_pose is None:
        return True
    a, b = np.asarray(twin_pose, dtype=np.float64), np.asarray(inventory_pose, dtype=np.float64)
    here = _position(a, twin_centre)
    there = _position(b, inventory_centre)
    assert here is not None and there is not None
    if np.linalg.norm(here - there) > DRIFT_TRANSLATION_M:
        return True
    return not symmetric and _rotation_deg(a, b) > DRIFT_ROTATION_DEG


def takes_inventory_pose(
    twin_pose: Any, twin_quality: Mapping[str, Any] | None, found_quality: Mapping[str, Any] | None
) -> bool:
    """Whether an inventory's pose (its ``pose_quality``) may replace an instance's pose (and
    its quality): a verified one always, any where the instance has none; an unverified one
    where the instance's pose is an unverified estimate too, as the newer of the two. A pose
    without figures (given by the twin platform or by hand) gives way to verified ones only."""
    if twin_pose is None or bool((found_quality or {}).get("verified")):
        return True
    return (
        found_quality is not None and twin_quality is not None and not twin_quality.get("verified")
    )


def _verified(quality: Mapping[str, Any] | None) -> bool:
    return bool((quality or {}).get("verified"))


def _refreshes(instance: TwinInstance, obj: SnapshotObject, head_id: str) -> bool:
    """Whether the inventory's pose of ``obj`` replaces the instance's (see the module
    docstring): :func:`takes_inventory_pose` and :func:`moved_beyond_noise`; an instance the
    comparison of the same snapshot just posed gives way to a verified pose only, and only
    when its own is unverified: both were estimated from the same capture."""
    if obj.pose is None:
        return False
    if instance.since_snapshot_id == head_id:
        may = _verified(obj.pose_quality) and not _verified(instance.pose_quality)
    else:
        may = takes_inventory_pose(instance.pose, instance.pose_quality, obj.pose_quality)
    return may and moved_beyond_noise(
        instance.pose,
        obj.pose,
        instance.centroid_env,
        obj.centroid_env,
        bool((obj.pose_quality or {}).get("ambiguous")),
    )


def _restore(
    session: Session, instance: TwinInstance, head_id: str, comparison_id: str, obj: SnapshotObject
) -> None:
    """Reopen an instance the comparison removed but the same snapshot's inventory shows
    where it stood, with a record ``restored`` (the inventory's pose where it may replace
    the instance's, else the instance's own)."""
    instance.closed_snapshot_id, instance.closed_at = None, None
    if _refreshes(instance, obj, head_id):
        _note(session, instance, head_id, comparison_id, TwinEdit.restored, obj)
    else:
        kind, pose, centre = TwinEdit.restored, instance.pose, instance.centroid_env
        _record(session, instance.id, head_id, comparison_id, kind, pose, centre)


def confirm(
    session: Session, env: Environment, head: Snapshot, comparison_id: str | None
) -> dict[str, list[TwinInstance]]:
    """A later snapshot's inventory against the twin as its comparison left it (see the
    module docstring); returns the instances ``seen``, ``drifted``, ``restored`` and
    ``added``."""
    found = objects_of(session, head.id)
    out: dict[str, list[TwinInstance]] = {"seen": [], "drifted": [], "restored": [], "added": []}
    if not found:
        return out
    library = objects.by_names(session, sorted({o.object_name for o in found}))
    matched = _pairs(open_instances(session, env.id), found, library)
    for instance, obj in matched:
        obj.instance_id = instance.id
        out["seen"].append(instance)
        if _refreshes(instance, obj, head.id):
            _note(session, instance, head.id, comparison_id, TwinEdit.drifted, obj)
            out["drifted"].append(instance)
    paired = {id(obj) for _, obj in matched}
    if comparison_id is not None:
        left = [obj for obj in found if id(obj) not in paired and obj.pose is not None]
        removed = removed_instances(session, head.id, comparison_id)
        for instance, obj in _pairs(removed, left, library):
            _restore(session, instance, head.id, comparison_id, obj)
            obj.instance_id = instance.id
            paired.add(id(obj))
            out["restored"].append(instance)
    for obj in found:
        if id(obj) in paired or obj.pose is None:
            continue
        instance = _create(session, env, head.id, comparison_id, obj)
        obj.instance_id = instance.id
        out["added"].append(instance)
    session.flush()
    return out
