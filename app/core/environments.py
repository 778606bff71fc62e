"""Environments: a named place with its detector classes and the reference that fixes its
frame (printed ArUco markers), plus options for its comparisons."""

from __future__ import annotations

import re
from typing import Any

import numpy as np
from sqlalchemy import func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from app.core.errors import Conflict, InvalidInput, NotFound
from app.core.jsondoc import show
from app.core.models import Environment
from app.core.options import check_environment_options

ARUCO_DICTIONARIES = {
    f"DICT_{bits}X{bits}_{n}" for bits in (4, 5, 6, 7) for n in (50, 100, 250, 1000)
} | {"DICT_ARUCO_ORIGINAL"}
MARKER_ID = re.compile(r"[0-9]{1,9}")


def dictionary_size(dictionary: str) -> int:
    """How many markers an ArUco dictionary holds: ids are 0..size-1."""
    return 1024 if dictionary == "DICT_ARUCO_ORIGINAL" else int(dictionary.rsplit("_", 1)[1])


def check_rigid(matrix: Any, where: str) -> list[list[float]]:
    """A 4×4 rigid transform as nested lists; InvalidInput naming ``where`` otherwise."""
    try:
        m = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as exc:
        raise InvalidInput(f"{where}: not a numeric 4×4 matrix") from exc
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise InvalidInput(f"{where}: expected a 4×4 matrix of finite numbers, got shape {m.shape}")
    if not np.allclose(m[3], [0, 0, 0, 1], atol=1e-6):
        raise InvalidInput(f"{where}: last row must be [0, 0, 0, 1]")
    r = m[:3, :3]
    if not np.allclose(r.T @ r, np.eye(3), atol=1e-4) or np.linalg.det(r) < 0:
        raise InvalidInput(f"{where}: the 3×3 block is not a rotation (orthonormal, det +1)")
    return [[float(v) for v in row] for row in m]


def check_classes(classes: list[str]) -> list[str]:
    if not classes:
        raise InvalidInput("classes: give at least one detector class name")
    cleaned = [c.strip() for c in classes]
    if any(not c for c in cleaned):
        raise InvalidInput("classes: names must not be empty")
    dupes = sorted({c for c in cleaned if cleaned.count(c) > 1})
    if dupes:
        raise InvalidInput(f"classes: duplicate names {dupes}")
    return cleaned


def check_reference(reference: dict[str, Any] | None) -> dict[str, Any] | None:
    """Validate the reference-marker sheet (docs/contract.md); returns it normalised."""
    if reference is None:
        return None
    markers = reference.get("markers")
    if not isinstance(markers, dict):
        raise InvalidInput("reference: expected {'markers': {'dictionary', 'size', 'poses'}}")
    dictionary = markers.get("dictionary", "DICT_4X4_50")
    if not isinstance(dictionary, str) or dictionary not in ARUCO_DICTIONARIES:
        raise InvalidInput(
            f"reference.markers.dictionary: unknown ArUco dictionary {show(dictionary)}"
        )
    size = markers.get("size")
    if not isinstance(size, int | float) or isinstance(size, bool) or not 0 < size < 10:
        raise InvalidInput("reference.markers.size: the marker side in metres, 0 < size < 10")
    poses = markers.get("poses")
    if not isinstance(poses, dict) or not poses:
        raise InvalidInput("reference.markers.poses: give at least one marker pose")
    n_markers = dictionary_size(dictionary)
    checked: dict[str, list[list[float]]] = {}
    for marker_id, pose in poses.items():
        # ASCII digits only: "²".isdigit() is True but int("²") fails, and a 5,000-digit id
        # is past int()'s limit.
        if not MARKER_ID.fullmatch(str(marker_id)):
            raise InvalidInput(
                f"reference.markers.poses: marker id {show(marker_id)} is not an integer"
            )
        number = int(marker_id)
        if number >= n_markers:
            raise InvalidInput(
                f"reference.markers.poses: marker id {number} is not in {dictionary} "
                f"(ids 0..{n_markers - 1})"
            )
        if str(number) in checked:
            raise InvalidInput(f"reference.markers.poses: marker id {number} is given twice")
        checked[str(number)] = check_rigid(pose, f"reference.markers.poses[{number}]")
    return {"markers": {"dictionary": dictionary, "size": float(size), "poses": checked}}


def create(
    session: Session,
    name: str,
    classes: list[str],
    reference: dict[str, Any] | None,
    options: dict[str, Any] | None,
) -> Environment:
    if session.scalar(select(func.count()).where(Environment.name == name)):
        raise Conflict(f"an environment named {name!r} already exists", code="EnvironmentExists")
    env = Environment(
        name=name,
        classes=check_classes(classes),
        reference=check_reference(reference),
        options=check_environment_options(options),
    )
    session.add(env)
    try:
        with session.begin_nested():
            session.flush()
    except IntegrityError as exc:
        raise Conflict(
            f"an environment named {name!r} already exists", code="EnvironmentExists"
        ) from exc
    return env


def get(session: Session, environment_id: str) -> Environment:
    env = session.get(Environment, environment_id)
    if env is None:
        raise NotFound(f"environment {environment_id} not found")
    return env


def list_all(session: Session) -> list[Environment]:
    return list(session.scalars(select(Environment).order_by(Environment.created_at)).all())
