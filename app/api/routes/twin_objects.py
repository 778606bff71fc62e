"""Seeding and correcting the twin by hand: instances the twin platform already knows, with
its own ids (``external_id``). Admin keys only (a key limited to environments reaches only
those); see :mod:`app.core.seeding` for where the records stand in the twin's seq order."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Body, Response, status

from app.api.deps import AdminKey, SessionDep
from app.api.schemas.common import ERRORS, TOO_LARGE, ErrorOut, conflict
from app.api.schemas.environments import InstanceCorrection, InstanceRead, InstanceSeed
from app.core import auth, seeding
from app.core.errors import InvalidInput

router = APIRouter(prefix="/environments", tags=["twin"], responses=ERRORS)

MAX_IMPORT_ROWS = 10_000
_REFUSED: dict[int | str, dict[str, Any]] = {
    422: {
        "model": ErrorOut,
        "description": "InvalidInput naming each bad row or field (unknown class, a pose "
        "that is not a finite rigid 4×4, an external id repeated or held by an open "
        "instance); nothing was written",
    }
}


def _seed(row: InstanceSeed) -> seeding.Seed:
    return seeding.Seed(object=row.object, pose=row.pose, external_id=row.external_id)


@router.post(
    "/{environment_id}/objects",
    status_code=status.HTTP_201_CREATED,
    responses={**TOO_LARGE, **_REFUSED},
)
def create_instance(
    environment_id: str, body: InstanceSeed, session: SessionDep, key: AdminKey
) -> InstanceRead:
    """Add one instance the twin platform knows (history record ``seeded``)."""
    auth.require_environment(key, environment_id)
    (instance,) = seeding.seed(session, environment_id, [_seed(body)], one=True)
    return InstanceRead.of(instance)


@router.post(
    "/{environment_id}/objects/import",
    status_code=status.HTTP_201_CREATED,
    responses={**TOO_LARGE, **_REFUSED},
)
def import_instances(
    environment_id: str,
    body: Annotated[list[InstanceSeed], Body(min_length=1, max_length=MAX_IMPORT_ROWS)],
    session: SessionDep,
    key: AdminKey,
) -> list[InstanceRead]:
    """Add many instances at once, all or nothing: a bad row is a 422 naming its index (from
    0) and nothing is written."""
    auth.require_environment(key, environment_id)
    created = seeding.seed(session, environment_id, [_seed(row) for row in body])
    return [InstanceRead.of(i) for i in created]


@router.patch(
    "/{environment_id}/objects/{instance_id}",
    responses={
        **TOO_LARGE,
        **_REFUSED,
        **conflict("InstanceClosed: the instance was removed or retired"),
    },
)
def correct_instance(
    environment_id: str,
    instance_id: str,
    body: InstanceCorrection,
    session: SessionDep,
    key: AdminKey,
) -> InstanceRead:
    """Correct an open instance's class, pose or external id (history record
    ``corrected``); a field left out is unchanged, ``"external_id": null`` clears it."""
    auth.require_environment(
        key,
        environment_id,
        detail=f"instance {instance_id} not found in environment {environment_id}",
    )
    given = body.model_fields_set
    if not given & {"object", "pose", "external_id"}:
        raise InvalidInput("give at least one of object, pose, external_id")
    if ("object" in given and body.object is None) or ("pose" in given and body.pose is None):
        raise InvalidInput("object and pose cannot be null (leave them out to keep them)")
    fields = {name: getattr(body, name) for name in ("object", "pose", "external_id")}
    instance = seeding.correct(
        session,
        environment_id,
        instance_id,
        **{name: value for name, value in fields.items() if name in given},
    )
    return InstanceRead.of(instance)


@router.delete(
    "/{environment_id}/objects/{instance_id}",
    status_code=status.HTTP_204_NO_CONTENT,
    responses=conflict(
        "InstanceClosed: it was already removed or retired; TwinHasNoSnapshot: it came "
        "from a snapshot the twin no longer reflects"
    ),
)
def retire_instance(
    environment_id: str, instance_id: str, session: SessionDep, key: AdminKey
) -> Response:
    """Close an instance by hand (history record ``retired``): it leaves the state from the
    snapshot the twin reflects; one seeded before the twin reflected any snapshot is
    deleted with its history."""
    auth.require_environment(
        key,
        environment_id,
        detail=f"instance {instance_id} not found in environment {environment_id}",
    )
    seeding.retire(session, environment_id, instance_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)
