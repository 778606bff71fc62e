"""The object job: sample a library model, measure its diameter, compute its features and
detect its symmetry (unless the user gave one); the artefacts are kept in storage so pose
estimation loads them instead of recomputing. They are published under this attempt's folder
(``objects/<id>/prepared/<job id>-<attempt>``) before the transaction that records them
(workers.runner.publish)."""

from __future__ import annotations

from dataclasses import dataclass

from sqlalchemy.orm import Session

from app.core import objects
from app.core.db import transaction
from app.core.enums import ObjectState
from workers.pipeline.model import MODEL_PRESETS, PreparedModel, prepare_model
from workers.pipeline.model.symmetry_group import spec_from_json, spec_to_json
from workers.runner import JobContext, Published, drop_stale, publish, run_job, unpublish


@dataclass(frozen=True)
class Prepared:
    """The prepared model and where its artefacts were published."""

    model: PreparedModel
    published: Published


def run(job_id: str) -> str:
    return run_job(job_id, _compute, _persist, unpublish)


def artifacts_root(object_id: str) -> str:
    """The folder holding each attempt's artefacts folder of the object."""
    return f"objects/{object_id}/prepared"


def _compute(ctx: JobContext) -> Prepared:
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
    published = publish(ctx, artifacts_root(object_id), ctx.work_dir / "prepared")
    return Prepared(model, published)


def _persist(session: Session, ctx: JobContext, prepared: Prepared) -> None:
    """Record the published artefacts (no bucket call here); other attempts' folders go
    after the commit."""
    object_id = ctx.job.object_id
    assert object_id is not None
    model, published = prepared.model, prepared.published
    drop_stale(session, ctx, published)
    obj = objects.get(session, object_id)
    obj.state = ObjectState.ready
    obj.diameter_m = float(model.diameter_m)
    obj.n_points = int(model.points.shape[0])
    obj.symmetry = spec_to_json(model.symmetry)
    obj.artifacts_key = published.folder
