"""Environments, their snapshot history, comparisons and twin state."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Request, Response, status

from app.api import negotiate
from app.api.deps import AdminKey, ReadKey, SessionDep, StorageDep
from app.api.schemas.common import ERRORS, TOO_LARGE, ErrorOut, conflict
from app.api.schemas.comparisons import ComparisonCreate, ComparisonRead
from app.api.schemas.environments import (
    EnvironmentCreate,
    EnvironmentRead,
    InstanceHistory,
    InstanceRead,
    PoseRecord,
    TwinProgressRead,
    TwinStateRead,
)
from app.api.schemas.exports import BINARY, GLB_MEDIA_TYPE, STATE_MEDIA_TYPES, StateFormat
from app.api.schemas.snapshots import SnapshotRead
from app.core import (
    auth,
    comparisons,
    environment_summary,
    environments,
    inventory,
    retention,
    snapshots,
    twin,
    twin_records,
)
from app.core.export import twin_scene

router = APIRouter(prefix="/environments", tags=["environments"], responses=ERRORS)


@router.post(
    "",
    status_code=status.HTTP_201_CREATED,
    responses={**TOO_LARGE, **conflict("EnvironmentExists: the name is taken")},
)
def create_environment(
    body: EnvironmentCreate, session: SessionDep, _key: AdminKey
) -> EnvironmentRead:
    """Create an environment with its detector classes and reference-marker sheet."""
    env = environments.create(session, body.name, body.classes, body.reference, body.options)
    summary = environment_summary.summaries(session, [env.id])[env.id]
    return EnvironmentRead.of(env, twin.progress(session, env), summary)


@router.get("")
def list_environments(session: SessionDep, key: ReadKey) -> list[EnvironmentRead]:
    """Every environment the key reaches, with its twin's object count and its newest
    snapshot."""
    reached = [e for e in environments.list_all(session) if auth.can_reach(key, e.id)]
    summary = environment_summary.summaries(session, [e.id for e in reached])
    return [EnvironmentRead.of(e, twin.progress(session, e), summary[e.id]) for e in reached]


@router.get("/{environment_id}")
def get_environment(environment_id: str, session: SessionDep, key: ReadKey) -> EnvironmentRead:
    """One environment."""
    auth.require_environment(key, environment_id)
    env = environments.get(session, environment_id)
    summary = environment_summary.summaries(session, [env.id])[env.id]
    return EnvironmentRead.of(env, twin.progress(session, env), summary)


@router.delete(
    "/{environment_id}",
    status_code=status.HTTP_204_NO_CONTENT,
    responses={409: {"model": ErrorOut, "description": "a job of it is queued or running"}},
)
def delete_environment(
    environment_id: str, session: SessionDep, storage: StorageDep, key: AdminKey
) -> Response:
    """Delete the environment with its snapshots, files, comparisons, twin and webhooks
    (204; 409 JobsActive while any of its jobs is queued or running)."""
    auth.require_environment(key, environment_id)
    retention.delete_environment(session, storage, environment_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)


@router.get("/{environment_id}/snapshots")
def list_snapshots(environment_id: str, session: SessionDep, key: ReadKey) -> list[SnapshotRead]:
    """The environment's snapshot history, newest first."""
    auth.require_environment(key, environment_id)
    environments.get(session, environment_id)
    return [
        SnapshotRead.of(
            s, snapshots.job_of(session, s.id), snapshots.automatic_comparison_of(session, s.id)
        )
        for s in snapshots.history(session, environment_id)
    ]


@router.post(
    "/{environment_id}/comparisons",
    status_code=status.HTTP_202_ACCEPTED,
    responses={
        **TOO_LARGE,
        **conflict("SnapshotNotReconstructed: before or after is not reconstructed"),
    },
)
def create_comparison(
    environment_id: str,
    body: ComparisonCreate,
    session: SessionDep,
    response: Response,
    key: AdminKey,
) -> ComparisonRead:
    """Compare two reconstructed snapshots (again) with other options."""
    auth.require_environment(key, environment_id)
    environments.get(session, environment_id)
    comparison = comparisons.create(
        session,
        environment_id,
        snapshots.get(session, body.before),
        snapshots.get(session, body.after),
        body.options,
    )
    response.headers["Location"] = f"/v1/jobs/{comparison.job_id}"
    return ComparisonRead.of(comparison)


@router.get("/{environment_id}/comparisons")
def list_comparisons(
    environment_id: str, session: SessionDep, key: ReadKey
) -> list[ComparisonRead]:
    """Every comparison of the environment, newest first."""
    auth.require_environment(key, environment_id)
    environments.get(session, environment_id)
    found = comparisons.list_for(session, environment_id)
    ext = twin_records.comparison_external_ids(session, found)
    return [ComparisonRead.of(c, ext) for c in found]


@router.get(
    "/{environment_id}/state",
    response_model=TwinStateRead,
    responses={
        200: {
            "description": "JSON, or binary glTF 2.0 (format=glb or Accept: model/gltf-binary)",
            "content": {GLB_MEDIA_TYPE: BINARY},
        },
        406: {"model": ErrorOut, "description": "Accept allows neither JSON nor glTF"},
        **conflict("SnapshotNotApplied: the twin has not reflected that snapshot"),
    },
)
def get_state(
    environment_id: str,
    request: Request,
    response: Response,
    session: SessionDep,
    storage: StorageDep,
    key: ReadKey,
    format: Annotated[
        StateFormat | None,
        Query(description="json or glb; overrides Accept (default: by Accept, else json)"),
    ] = None,
    snapshot: Annotated[
        str | None,
        Query(
            max_length=36,
            description="a snapshot of this environment (its twin_update baseline or "
            "applied): the twin as it stood once that snapshot was taken into account",
        ),
    ] = None,
) -> TwinStateRead | Response:
    """The twin as it stands (or at ``snapshot``): every instance present with its pose, as
    JSON or as a binary glTF scene of the library models (docs/contract.md, "Export")."""
    auth.require_environment(key, environment_id)
    env = environments.get(session, environment_id)
    chosen = (
        format
        or STATE_MEDIA_TYPES[
            negotiate.choose(request.headers.get("accept"), list(STATE_MEDIA_TYPES))
        ]
    )
    state = twin_scene.view(session, env, snapshot)
    response.headers["Vary"] = "Accept"
    if chosen == StateFormat.glb:
        name = f"{environment_id}-{state.seq}.glb"
        return Response(
            twin_scene.glb(session, storage, state),
            media_type=GLB_MEDIA_TYPE,
            headers={"Content-Disposition": f'attachment; filename="{name}"', "Vary": "Accept"},
        )
    # sightings of the twin as it stands only: a past state's would name later snapshots
    sightings = (
        {}
        if state.at_snapshot
        else inventory.last_seen(session, (i.instance_id for i in state.instances))
    )
    return TwinStateRead(
        environment=environment_id,
        twin=TwinProgressRead.of(twin.progress(session, env)),
        at_snapshot=state.snapshot_id if state.at_snapshot else None,
        objects=[
            InstanceRead(
                instance_id=i.instance_id,
                external_id=i.external_id,
                object=i.object_name,
                object_id=i.object_id,
                pose=i.pose,
                pose_quality=i.pose_quality,
                since_snapshot=i.since_snapshot,
                created_snapshot=i.created_snapshot,
                created_at=i.created_at,
                last_seen_snapshot=sightings.get(i.instance_id),
                seen=(
                    sightings.get(i.instance_id) == state.snapshot_id
                    if state.snapshot_id and not state.at_snapshot
                    else None
                ),
            )
            for i in state.instances
        ],
    )


@router.get("/{environment_id}/objects/{instance_id}/history")
def get_instance_history(
    environment_id: str, instance_id: str, session: SessionDep, key: ReadKey
) -> InstanceHistory:
    """Every pose an instance has had, with the snapshot that saw it."""
    auth.require_environment(
        key,
        environment_id,
        detail=f"instance {instance_id} not found in environment {environment_id}",
    )
    instance, poses = twin.history(session, environment_id, instance_id)
    return InstanceHistory(
        instance_id=instance.id,
        external_id=instance.external_id,
        object=instance.object_name,
        created_snapshot=instance.created_snapshot_id,
        closed_snapshot=instance.closed_snapshot_id,
        poses=[
            PoseRecord(
                snapshot=p.snapshot_id,
                comparison=p.comparison_id,
                change_type=p.change_type,
                pose=p.pose,
                at=p.created_at,
            )
            for p in poses
        ],
    )
