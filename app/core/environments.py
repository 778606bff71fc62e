"""Environments: a named place with its detector classes and the reference that fixes its
frame (printed ArUco markers), plus options for its comparisons."""

from __future__ import annotations

from typing import Any

from sqlalchemy import func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from app.core.errors import Conflict, InvalidInput, NotFound
from app.core.models import Environment
from app.core.options import check_environment_options
from app.formats import FormatError
from app.formats.reference import read_reference


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
    """Validate the reference-marker sheet (:mod:`app.formats.reference`); returns it
    normalised."""
    try:
        sheet = read_reference(reference)
    except FormatError as exc:
        raise InvalidInput(exc.detail) from exc
    return None if sheet is None else sheet.to_json()


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
