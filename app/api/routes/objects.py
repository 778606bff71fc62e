"""The object library (admin to change, read to list)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, File, Form, Response, UploadFile, status

from app.api.deps import AdminKey, ReadKey, SessionDep, SettingsDep, StorageDep
from app.api.schemas.common import ERRORS, MALFORMED, TOO_LARGE, ErrorOut, conflict
from app.api.schemas.exports import BINARY, GLB_MEDIA_TYPE
from app.api.schemas.objects import ObjectRead
from app.core import objects
from app.core.db import get_read_session_factory
from app.core.errors import Conflict
from app.core.export import gltf, twin_scene
from app.core.export.ply import PlyError

router = APIRouter(prefix="/objects", tags=["objects"], responses=ERRORS)


def model_upload(
    file: Annotated[UploadFile, File(description=".ply .obj .stl .glb .off .pcd")],
    name: Annotated[str, Form(description="the detector class name")],
    units: Annotated[str, Form(description="m, cm or mm")] = "m",
    symmetry: Annotated[str, Form(description="auto, none, or a JSON spec")] = "auto",
) -> objects.ModelUpload:
    """The multipart form of ``POST /objects`` (its fields, in this order, are the request
    body in the OpenAPI document)."""
    return objects.ModelUpload(
        name=name, filename=file.filename or "", source=file.file, units=units, symmetry=symmetry
    )


@router.post(
    "",
    status_code=status.HTTP_202_ACCEPTED,
    responses={
        **MALFORMED,
        **TOO_LARGE,
        **conflict("ObjectExists: the name is taken"),
        507: {"model": ErrorOut, "description": "storage full: nothing was kept, retry later"},
    },
)
def create_object(
    session: SessionDep,
    storage: StorageDep,
    settings: SettingsDep,
    response: Response,
    _key: AdminKey,
    upload: Annotated[objects.ModelUpload, Depends(model_upload)],
) -> ObjectRead:
    """Add a model to the library; a job samples it, measures its diameter and detects its
    symmetry (poll the job, or GET the object until `state` is `ready`)."""
    obj, job = objects.create(
        session,
        storage,
        upload,
        max_bytes=settings.max_file_bytes,
        lookup=get_read_session_factory(),  # the write lock only for the insert (SQLite)
    )
    response.headers["Location"] = f"/v1/jobs/{job.id}"
    return ObjectRead.of(obj, job)


@router.get("")
def list_objects(session: SessionDep, _key: ReadKey) -> list[ObjectRead]:
    """Every live library object, by name."""
    return [ObjectRead.of(o, objects.latest_job(session, o.id)) for o in objects.list_live(session)]


@router.get("/{object_id}")
def get_object(object_id: str, session: SessionDep, _key: ReadKey) -> ObjectRead:
    """One library object with its diameter and symmetry."""
    obj = objects.get(session, object_id)
    return ObjectRead.of(obj, objects.latest_job(session, obj.id))


@router.get(
    "/{object_id}/model",
    response_class=Response,
    responses={
        200: {"description": "binary glTF 2.0", "content": {GLB_MEDIA_TYPE: BINARY}},
        **conflict(
            "ModelNotReady: the model is not prepared yet; ModelUnreadable: the stored model "
            "cannot be read"
        ),
    },
)
def get_object_model(
    object_id: str, session: SessionDep, storage: StorageDep, _key: ReadKey
) -> Response:
    """The library object's model as binary glTF: object frame, metres, +z up as stored (no
    node transform); a mesh, or points for a cloud model."""
    obj = objects.get(session, object_id)
    try:
        model = twin_scene.load_model(storage, obj)
    except FileNotFoundError as exc:
        raise Conflict(
            f"object {object_id} has no prepared model yet (state {obj.state})",
            code="ModelNotReady",
        ) from exc
    except (PlyError, gltf.ModelGeometryError, OSError) as exc:
        raise Conflict(
            f"object {object_id}: the model cannot be read ({exc})", code="ModelUnreadable"
        ) from exc
    extras = {"object_id": obj.id, "class": obj.name, "frame": "object, metres, +z up"}
    return Response(
        gltf.model_glb(obj.name, model, extras, twin_scene.generator()),
        media_type=GLB_MEDIA_TYPE,
        headers={"Cache-Control": "private, max-age=300"},
    )


@router.delete("/{object_id}")
def delete_object(object_id: str, session: SessionDep, _key: AdminKey) -> ObjectRead:
    """Remove an object from the library; past comparisons keep their records."""
    return ObjectRead.of(objects.delete(session, object_id), None)
