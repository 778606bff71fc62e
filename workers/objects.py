"""The object job: sample a library model, measure its diameter, compute its features and
detect its symmetry (unless the user gave one); the artefacts are kept in storage so pose
estimation loads them instead of recomputing."""

from __future__ import annotations

from pathlib import Path

from sqlalchemy.orm import Session

from app.core import objects
from app.core.db import transaction
from app.core.enums import ObjectState
from workers.pipeline.model import MODEL_PRESETS, PreparedModel, prepare_model
from workers.pipeline.model.symmetry_group import spec_from_json, spec_to_json
from workers.runner import JobContext, run_job


def run(job_id: str) -> str:
    return run_job(job_id, _compute, _persist)


def artifacts_key(object_id: str) -> str:
    return f"objects/{object_id}/prepared"


def _compute(ctx: JobContext) -> PreparedModel:
    object_id = ctx.job.object_id
    if object_id is None:
        raise ValueError(f"job {ctx.job.id} has no object")
    with transaction() as session:
        obj = objects.get(session, object_id)
        name, units, file_key = obj.name, obj.units, obj.file_key
        requested = dict(obj.symmetry_requested or {})
    ctx.progress("prepare", 0.0)
    kind = requested.get("kind", "auto")
    symmetry = None if kind == "auto" else spec_from_json(requested)
    model = prepare_model(
        ctx.storage.local_file(file_key),
        ctx.work_dir / "prepared",
        MODEL_PRESETS[ctx.job.preset if ctx.job.preset in MODEL_PRESETS else "default"],
        units=units,
        symmetry=symmetry,
        name=name,
    )
    ctx.progress("prepare", 1.0)
    return model


def _persist(session: Session, ctx: JobContext, model: PreparedModel) -> None:
    object_id = ctx.job.object_id
    assert object_id is not None
    key = artifacts_key(object_id)
    ctx.storage.delete_prefix(key)
    ctx.storage.move_in(Path(ctx.work_dir / "prepared"), key)
    obj = objects.get(session, object_id)
    obj.state = ObjectState.ready
    obj.diameter_m = float(model.diameter_m)
    obj.n_points = int(model.points.shape[0])
    obj.symmetry = spec_to_json(model.symmetry)
    obj.artifacts_key = key
