"""Seeding and correcting the twin by hand: instances the twin platform already knows, with
its own ids (``external_id``). Admin keys only (a key limited to environments reaches only
those); see :mod:`app.core.seeding` for where the records stand in the twin's seq order."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Depends, Request, Response, status
from pydantic import TypeAdapter, ValidationError

from app.api.deps import AdminKey, SessionDep
from app.api.schemas.common import ERRORS, TOO_LARGE, ErrorOut, conflict
from app.api.schemas.environments import InstanceCorrection, InstanceRead, InstanceSeed
from app.core import auth, seeding
from app.core.errors import InvalidInput, UnsupportedMedia

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


_ROWS = TypeAdapter(list[InstanceSeed])


async def import_rows(request: Request) -> list[seeding.Seed]:
    """The rows of an import: a JSON list of :class:`InstanceSeed` or, with ``Content-Type:
    text/csv``, :func:`app.core.seeding.parse_csv`'s CSV; 1 to :data:`MAX_IMPORT_ROWS`."""
    kind = request.headers.get("content-type", "application/json").split(";")[0].strip()
    body = await request.body()
    if kind == "text/csv":
        rows = seeding.parse_csv(body)
    elif kind == "application/json":
        try:
            rows = [_seed(row) for row in _ROWS.validate_json(body)]
        except ValidationError as exc:
            raise InvalidInput(_validation_detail(exc)) from exc
    else:
        raise UnsupportedMedia(f"send application/json or text/csv, not {kind}")
    if not 1 <= len(rows) <= MAX_IMPORT_ROWS:
        raise InvalidInput(f"an import holds 1 to {MAX_IMPORT_ROWS} rows, not {len(rows)}")
    return rows


def _validation_detail(exc: ValidationError) -> str:
    """Pydantic's errors named as the import's other 422s: ``row 7: pose: <message>``."""
    parts = []
    for err in exc.errors()[: seeding.MAX_PROBLEMS]:
        loc = list(err.get("loc", ()))
        row = f"row {loc.pop(0)}: " if loc and isinstance(loc[0], int) else ""
        where = ".".join(str(p) for p in loc)
        parts.append(f"{row}{where}: {err.get('msg')}" if where else f"{row}{err.get('msg')}")
    return "nothing was written: " + "; ".join(parts)


_IMPORT_BODY = {
    "requestBody": {
        "required": True,
        "content": {
            "application/json": {
                "schema": {
                    "type": "array",
                    "items": {"$ref": "#/components/schemas/InstanceSeed"},
                    "minItems": 1,
                    "maxItems": MAX_IMPORT_ROWS,
                }
            },
            "text/csv": {
                "schema": {"type": "string"},
                "example": "object,external_id,m00,m01,m02,m03,m10,m11,m12,m13,m20,m21,m22,"
                "m23,m30,m31,m32,m33\nmug,urn:cell-2:mug-3,1,0,0,0.4,0,1,0,1.1,0,0,1,0.8,0,0,0,1\n",
            },
        },
    }
}


@router.post(
    "/{environment_id}/objects/import",
    status_code=status.HTTP_201_CREATED,
    openapi_extra=_IMPORT_BODY,
    responses={
        **TOO_LARGE,
        **_REFUSED,
        415: {"model": ErrorOut, "description": "neither application/json nor text/csv"},
    },
)
def import_instances(
    environment_id: str,
    session: SessionDep,
    key: AdminKey,
    rows: Annotated[list[seeding.Seed], Depends(import_rows)],
) -> list[InstanceRead]:
    """Add many instances at once (a JSON list, or CSV with columns object, external_id,
    m00..m33), all or nothing: a bad row is a 422 naming its index (from 0) and nothing is
    written."""
    auth.require_environment(key, environment_id)
    created = seeding.seed(session, environment_id, rows)
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
    fields = {"object": "object_class", "pose": "pose", "external_id": "external_id"}
    instance = seeding.correct(
        session,
        environment_id,
        instance_id,
        **{arg: getattr(body, name) for name, arg in fields.items() if name in given},
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
