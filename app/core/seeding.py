"""Seeding and correcting the twin from the twin platform, which already knows its objects
and has its own ids for them (``external_id``).

Where a hand-made record stands in the twin's seq order: it belongs to the snapshot the twin
reflects when it is made (``Environment.twin_snapshot_id``, the "before" of the next
automatic comparison), or to no snapshot before the twin reflects any (such an instance
stands from the start: ``state_at`` counts it at every seq). The next automatic comparison
therefore reads a seeded instance as part of its "before" twin and matches it like any
other: a ``removed`` change at its place closes it, a ``moved`` one updates it. A
comparison already queued or running read the twin before the seed and does not see it.

Every function locks the environment row as :func:`app.core.twin.advance` does, so a seed
and the chain never interleave. None commits.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from sqlalchemy import delete, select
from sqlalchemy.orm import Session

from app.core.enums import TwinEdit
from app.core.errors import Conflict, InvalidInput, NotFound
from app.core.models import (
    Environment,
    InstancePose,
    LibraryObject,
    TwinInstance,
    utcnow,
)

EXTERNAL_ID_MAX = 200
ROTATION_TOL = 1e-3  # max |R Rᵀ - I| entry and |det R - 1|: poses printed to 4+ decimals pass
MAX_PROBLEMS = 20  # problems named in one 422


@dataclass(frozen=True)
class Seed:
    """One instance to create: ``object`` a class name of the environment or a library
    object id, ``pose`` ``env_from_object`` (4×4, metres), ``external_id`` the platform's
    id or None."""

    object: str
    pose: Any
    external_id: str | None = None


def check_pose(value: Any) -> list[list[float]]:
    """``value`` as a finite rigid 4×4 (``env_from_object``, metres): rotation block
    orthonormal within :data:`ROTATION_TOL` with determinant +1, last row ``0 0 0 1``;
    returned with that block replaced by the nearest rotation (SVD), so that rounding in
    the platform's numbers never leaves a non-rigid pose in the twin. Raises ValueError
    naming the problem."""
    if not (
        isinstance(value, list | tuple)
        and len(value) == 4
        and all(isinstance(row, list | tuple) and len(row) == 4 for row in value)
    ):
        raise ValueError("pose must be a 4×4 matrix (four rows of four numbers)")
    if not all(_number(v) for row in value for v in row):
        raise ValueError("pose must hold finite numbers only (no NaN, infinity or strings)")
    m = np.asarray(value, dtype=np.float64)
    r = m[:3, :3]
    if np.abs(r @ r.T - np.eye(3)).max() > ROTATION_TOL:
        raise ValueError("pose is not rigid: its 3×3 rotation block is not orthonormal")
    if abs(float(np.linalg.det(r)) - 1.0) > ROTATION_TOL:
        raise ValueError("pose is not rigid: its rotation block has determinant -1 (a mirror)")
    if not np.array_equal(m[3], [0.0, 0.0, 0.0, 1.0]):
        raise ValueError("pose's last row must be [0, 0, 0, 1]")
    u, _, vt = np.linalg.svd(r)
    m[:3, :3] = u @ vt  # the nearest rotation: the twin holds rigid poses only
    return [[float(v) for v in row] for row in m]


def _number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def check_external_id(value: Any) -> str:
    """A platform id: a string of 1 to :data:`EXTERNAL_ID_MAX` characters, no control
    characters, no leading or trailing whitespace. Raises ValueError."""
    if not isinstance(value, str) or not value:
        raise ValueError("external_id must be a non-empty string")
    if len(value) > EXTERNAL_ID_MAX:
        raise ValueError(f"external_id is longer than {EXTERNAL_ID_MAX} characters")
    if any(ord(c) < 0x20 or 0x7F <= ord(c) <= 0x9F for c in value) or value != value.strip():
        raise ValueError("external_id has control characters or surrounding whitespace")
    return value


CSV_POSE_COLUMNS = tuple(f"m{r}{c}" for r in range(4) for c in range(4))


def parse_csv(data: bytes) -> list[Seed]:
    """The rows of a CSV import (UTF-8, optional BOM; a header row, then one instance per
    row): columns ``object``, ``m00`` … ``m33`` (the pose, row-major, metres) and
    optionally ``external_id`` (an empty cell: none); other columns are ignored. Raises
    InvalidInput naming the header's problem, or every row whose cells are not numbers
    (rows numbered from 0, the first after the header; blank lines skipped)."""
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InvalidInput(f"the CSV is not UTF-8 (byte {exc.start})") from exc
    reader = csv.DictReader(io.StringIO(text, newline=""))
    header = reader.fieldnames or []
    missing = [name for name in ("object", *CSV_POSE_COLUMNS) if name not in header]
    if missing:
        raise InvalidInput(f"the CSV header lacks {', '.join(missing)} (got {header})")
    rows: list[Seed] = []
    problems: list[str] = []
    try:
        for i, cells in enumerate(reader):
            try:
                pose = [[float(cells[f"m{r}{c}"] or "") for c in range(4)] for r in range(4)]
            except (TypeError, ValueError):
                problems.append(f"row {i} (line {reader.line_num}): a pose cell is not a number")
                continue
            ext = cells.get("external_id") or None
            rows.append(Seed(object=str(cells["object"] or ""), pose=pose, external_id=ext))
    except csv.Error as exc:
        raise InvalidInput(f"the CSV cannot be read at line {reader.line_num}: {exc}") from exc
    if problems:
        raise InvalidInput("nothing was written: " + "; ".join(problems[:MAX_PROBLEMS]))
    return rows


def _lock(session: Session, environment_id: str) -> Environment:
    env = session.scalar(
        select(Environment)
        .where(Environment.id == environment_id)
        .with_for_update(key_share=True)
        .execution_options(populate_existing=True)
    )
    if env is None:
        raise NotFound(f"environment {environment_id} not found")
    return env


def _open_external_ids(session: Session, environment_id: str) -> dict[str, str]:
    """external id → instance id of the environment's open instances that have one."""
    rows = session.execute(
        select(TwinInstance.external_id, TwinInstance.id).where(
            TwinInstance.environment_id == environment_id,
            TwinInstance.closed_snapshot_id.is_(None),
            TwinInstance.external_id.is_not(None),
        )
    ).all()
    return {str(ext): str(iid) for ext, iid in rows}


class _Classes:
    """The environment's classes and the live library objects that name them."""

    def __init__(self, session: Session, env: Environment) -> None:
        self.names = set(env.classes)
        live = session.scalars(
            select(LibraryObject).where(
                LibraryObject.name.in_(list(self.names)), LibraryObject.deleted_at.is_(None)
            )
        ).all()
        self.by_name = {o.name: o.id for o in live}
        self.by_id = {o.id: o.name for o in live}

    def resolve(self, value: Any) -> tuple[str, str | None]:
        """(class name, library object id or None) of a class name or a library object id
        of one of the environment's classes; ValueError when it is neither."""
        if not isinstance(value, str) or not value:
            raise ValueError("object must be a class name or a library object id")
        name = self.by_id.get(value, value)
        if name not in self.names:
            raise ValueError(
                f"unknown class {value!r}: not one of the environment's classes "
                f"{sorted(self.names)} nor the library object id of one"
            )
        return name, self.by_name.get(name)


_Checked = tuple[str, str | None, list[list[float]], str | None]


def _check_rows(
    session: Session, env: Environment, rows: Sequence[Seed]
) -> tuple[list[_Checked], list[tuple[int, str]]]:
    """Each row as (class name, library object id, pose, external id), and the problems
    found as (row index, what is wrong)."""
    classes = _Classes(session, env)
    taken = _open_external_ids(session, env.id)
    seen: dict[str, int] = {}
    problems: list[tuple[int, str]] = []
    checked: list[_Checked] = []
    for i, row in enumerate(rows):
        try:
            name, object_id = classes.resolve(row.object)
            pose = check_pose(row.pose)
            ext = None if row.external_id is None else check_external_id(row.external_id)
            if ext is not None and ext in seen:
                raise ValueError(f"external_id {ext!r} repeats row {seen[ext]}")
            if ext is not None and ext in taken:
                raise ValueError(f"external_id {ext!r} is held by open instance {taken[ext]}")
        except ValueError as exc:
            problems.append((i, str(exc)))
            continue
        if ext is not None:
            seen[ext] = i
        checked.append((name, object_id, pose, ext))
    return checked, problems


def seed(
    session: Session, environment_id: str, rows: Sequence[Seed], *, one: bool = False
) -> list[TwinInstance]:
    """Create one open instance per row, all or nothing, each with a ``seeded`` history
    record (module docstring: which snapshot they belong to). Raises NotFound for the
    environment and InvalidInput (422) naming every bad row by its index from 0 (``one``:
    a single instance, its problem without a row number): an unknown class, a pose that is
    not a finite rigid 4×4, an external id that is malformed, repeated in the rows or held
    by an open instance."""
    env = _lock(session, environment_id)
    checked, problems = _check_rows(session, env, rows)
    if problems and one:
        raise InvalidInput(f"nothing was written: {problems[0][1]}")
    if problems:
        named = [f"row {i}: {what}" for i, what in problems[:MAX_PROBLEMS]]
        more = len(problems) - len(named)
        raise InvalidInput(
            f"{len(problems)} of {len(rows)} rows refused, nothing was written: "
            + "; ".join(named)
            + (f"; and {more} more" if more > 0 else "")
        )
    anchor = env.twin_snapshot_id
    created = [
        TwinInstance(
            environment_id=environment_id,
            object_name=name,
            object_id=object_id,
            external_id=ext,
            pose=pose,
            since_snapshot_id=anchor,
            created_snapshot_id=anchor,
        )
        for name, object_id, pose, ext in checked
    ]
    session.add_all(created)
    session.flush()
    for instance in created:
        _record(session, instance, anchor, TwinEdit.seeded)
    session.flush()
    return created


def _record(
    session: Session, instance: TwinInstance, snapshot_id: str | None, kind: TwinEdit
) -> None:
    session.add(
        InstancePose(
            instance_id=instance.id,
            snapshot_id=snapshot_id,
            comparison_id=None,
            change_type=kind,
            pose=instance.pose,
            centroid_env=instance.centroid_env,
        )
    )


def _open_instance(session: Session, environment_id: str, instance_id: str) -> TwinInstance:
    instance = session.get(TwinInstance, instance_id, populate_existing=True)
    if instance is None or instance.environment_id != environment_id:
        raise NotFound(f"instance {instance_id} not found in environment {environment_id}")
    if instance.closed_snapshot_id is not None:
        raise Conflict(
            f"instance {instance_id} was closed at snapshot {instance.closed_snapshot_id}",
            code="InstanceClosed",
        )
    return instance


_UNSET: Any = object()


def correct(
    session: Session,
    environment_id: str,
    instance_id: str,
    *,
    object_class: Any = _UNSET,
    pose: Any = _UNSET,
    external_id: Any = _UNSET,
) -> TwinInstance:
    """Set an open instance's class (``object_class``: a class name or library object id),
    pose and/or external id (None clears it), all or none, and add a ``corrected`` history
    record with the pose it then has. A new pose holds from the snapshot the twin reflects.
    Raises NotFound, Conflict (InstanceClosed: it was removed) and InvalidInput naming the
    field (unknown class, bad pose, an external id another open instance holds)."""
    env = _lock(session, environment_id)
    instance = _open_instance(session, environment_id, instance_id)
    try:
        if object_class is not _UNSET:
            object_class = _Classes(session, env).resolve(object_class)
        if pose is not _UNSET:
            pose = check_pose(pose)
        if external_id is not _UNSET and external_id is not None:
            external_id = check_external_id(external_id)
            holder = _open_external_ids(session, environment_id).get(external_id)
            if holder is not None and holder != instance.id:
                raise ValueError(f"external_id {external_id!r} is held by open instance {holder}")
    except ValueError as exc:
        raise InvalidInput(f"instance {instance_id}: nothing was changed: {exc}") from exc
    if object_class is not _UNSET:
        instance.object_name, instance.object_id = object_class
    if pose is not _UNSET:
        instance.pose, instance.pose_quality, instance.centroid_env = pose, None, None
        instance.since_snapshot_id = env.twin_snapshot_id
    if external_id is not _UNSET:
        instance.external_id = external_id
    _record(session, instance, env.twin_snapshot_id, TwinEdit.corrected)
    session.flush()
    return instance


def retire(session: Session, environment_id: str, instance_id: str) -> TwinInstance | None:
    """Close an open instance by hand at the snapshot the twin reflects, with a ``retired``
    history record; returns it. Before the twin reflects any snapshot the instance never
    stood in any state, so it is deleted with its history instead (returns None)."""
    env = _lock(session, environment_id)
    instance = _open_instance(session, environment_id, instance_id)
    if env.twin_snapshot_id is None:
        if instance.created_snapshot_id is not None:
            raise Conflict(
                f"instance {instance_id} stands since snapshot {instance.created_snapshot_id}"
                " but the twin reflects no snapshot now: retire it once it does",
                code="TwinHasNoSnapshot",
            )
        session.execute(delete(InstancePose).where(InstancePose.instance_id == instance.id))
        session.delete(instance)
        session.flush()
        return None
    instance.closed_snapshot_id, instance.closed_at = env.twin_snapshot_id, utcnow()
    session.add(
        InstancePose(
            instance_id=instance.id,
            snapshot_id=env.twin_snapshot_id,
            change_type=TwinEdit.retired,
        )
    )
    session.flush()
    return instance
