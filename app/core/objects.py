"""The object library: models of the things that can appear in an environment. Uploading
stores the file and queues a job that samples the model, measures it and detects its
symmetry (worker side)."""

from __future__ import annotations

import errno
import math
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import PurePosixPath
from typing import Any, BinaryIO

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from app.core import jobs, jsondoc
from app.core.enums import JobKind, JobState
from app.core.errors import (
    Conflict,
    InsufficientStorage,
    InvalidInput,
    NotFound,
    PayloadTooLarge,
)
from app.core.models import Job, LibraryObject, new_id, utcnow
from app.core.storage import Storage
from app.formats.ply import ply_count_problem

TASK = "object.prepare"
MODEL_SUFFIXES = {".ply", ".obj", ".stl", ".glb", ".off", ".pcd"}
UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001}
SYMMETRY_KINDS = {"auto", "none", "discrete", "continuous"}
SYMMETRY_KEYS = {"kind", "axis", "origin", "rotations", "appearance_breaks"}


def parse_symmetry(value: str | None) -> dict[str, Any]:
    """``auto`` (default), ``none`` or a JSON spec such as
    ``{"kind": "continuous", "axis": [0, 0, 1], "origin": [0, 0, 0]}`` or
    ``{"kind": "discrete", "rotations": [<4×4>, ...]}`` (optional ``appearance_breaks``),
    checked the way the worker will read it (finite non-zero axis, proper 4×4 rotations);
    InvalidInput naming the part (``symmetry.axis``) otherwise."""
    if value is None or value.strip() in {"", "auto"}:
        return {"kind": "auto"}
    if value.strip() == "none":
        return {"kind": "none"}
    spec = jsondoc.loads(value, "symmetry", root="symmetry")
    if not isinstance(spec, dict) or spec.get("kind") not in SYMMETRY_KINDS:
        raise InvalidInput(f"symmetry: 'kind' must be one of {sorted(SYMMETRY_KINDS)}")
    unknown = sorted(set(spec) - SYMMETRY_KEYS)
    if unknown:
        raise InvalidInput(
            f"symmetry: unknown key(s) {', '.join(jsondoc.show(k) for k in unknown[:5])}; "
            f"known: {', '.join(sorted(SYMMETRY_KEYS))}"
        )
    if not isinstance(spec.get("appearance_breaks", False), bool):
        raise InvalidInput("symmetry.appearance_breaks: true or false")
    if spec["kind"] == "continuous":
        axis = _vector(spec.get("axis"), "symmetry.axis")
        if sum(a * a for a in axis) ** 0.5 < 1e-9:
            raise InvalidInput("symmetry.axis: a non-zero 3-vector in the model frame")
        if "origin" in spec:
            _vector(spec["origin"], "symmetry.origin")
    rotations = spec.get("rotations")
    if spec["kind"] == "discrete" or rotations is not None:
        if not isinstance(rotations, list) or not rotations:
            raise InvalidInput("symmetry.rotations: a non-empty list of 4×4 rotation matrices")
        for i, matrix in enumerate(rotations):
            _rotation(matrix, f"symmetry.rotations[{i}]")
    return spec


def _vector(value: Any, where: str) -> list[float]:
    """Three finite numbers (not bools, not strings, not null)."""
    if not (isinstance(value, list) and len(value) == 3 and all(_finite(v) for v in value)):
        raise InvalidInput(f"{where}: three finite numbers [x, y, z], got {jsondoc.show(value)}")
    return [float(v) for v in value]


def _finite(value: Any) -> bool:
    return (
        isinstance(value, int | float)
        and not isinstance(value, bool)
        and abs(value) < jsondoc.INT_LIMIT
        and math.isfinite(value)
    )


def _rotation(matrix: Any, where: str) -> None:
    """A 4×4 proper rotation (about a point) with last row 0 0 0 1, with the worker's
    tolerances (``workers.pipeline.model.symmetry_group``)."""
    if not (
        isinstance(matrix, list)
        and len(matrix) == 4
        and all(
            isinstance(row, list) and len(row) == 4 and all(map(_finite, row)) for row in matrix
        )
    ):
        raise InvalidInput(f"{where}: a 4×4 matrix of finite numbers")
    m = np.asarray(matrix, dtype=np.float64)
    r = m[:3, :3]
    if not np.allclose(r @ r.T, np.eye(3), atol=1e-3) or np.linalg.det(r) < 0.99:
        raise InvalidInput(f"{where}: the 3×3 block is not a proper rotation")
    if not np.allclose(m[3], [0, 0, 0, 1], atol=1e-9):
        raise InvalidInput(f"{where}: the last row must be [0, 0, 0, 1]")


def format_problem(suffix: str, head: bytes, size_bytes: int) -> str | None:
    """Why the file's first bytes ``head`` cannot be a ``suffix`` model file, or None when
    they can. A cheap check of the format's signature at upload; a file that passes may
    still fail its preparation job (no triangles, non-finite vertices)."""
    text_like = b"\0" not in head
    stripped = head.lstrip()
    if suffix == ".ply" and not head.startswith(b"ply"):
        return "a PLY file starts with the line 'ply'"
    if suffix == ".ply":
        return _ply_count_problem(head, size_bytes)
    if suffix == ".glb" and not head.startswith(b"glTF"):
        return "a binary glTF (.glb) file starts with the bytes 'glTF'"
    if suffix == ".off":
        first = stripped.split(maxsplit=1)[0] if stripped else b""
        if not first.endswith(b"OFF"):
            return "an OFF file starts with the keyword OFF"
    if suffix == ".stl":
        binary = size_bytes >= 84 and len(head) >= 84
        count = int.from_bytes(head[80:84], "little") if binary else -1
        if not (stripped.startswith(b"solid") or size_bytes == 84 + 50 * count):
            return "neither ASCII STL ('solid ...') nor binary STL (84 + 50 × triangles bytes)"
    if suffix == ".obj" and not (text_like and b"v " in head):
        return "an OBJ file is text with vertex lines ('v x y z')"
    if suffix == ".pcd" and b"FIELDS" not in head[:4096]:
        return "a PCD file has a header with a FIELDS line"
    return None


def _ply_count_problem(head: bytes, size_bytes: int) -> str | None:
    """The PLY header's element counts against the file's size (the worker checks the same
    when it loads the file); a header longer than ``head`` is left to the worker."""
    if b"end_header" not in head and len(head) < size_bytes:
        return None
    return ply_count_problem(head, size_bytes)


def _check_name_free(session: Session, name: str) -> None:
    if session.scalar(
        select(LibraryObject.id).where(
            LibraryObject.name == name, LibraryObject.deleted_at.is_(None)
        )
    ):
        raise Conflict(f"an object named {name!r} already exists", code="ObjectExists")


@dataclass(frozen=True)
class ModelUpload:
    """A library object as uploaded: the detector class ``name``, the model file (its client
    ``filename``, whose suffix names the format, and a binary stream ``source``), its
    ``units`` (m, cm or mm) and the requested ``symmetry`` (``auto``, ``none``, a JSON spec,
    or None for auto)."""

    name: str
    filename: str
    source: BinaryIO
    units: str
    symmetry: str | None


def create(
    session: Session,
    storage: Storage,
    upload: ModelUpload,
    *,
    max_bytes: int,
    lookup: sessionmaker[Session] | None = None,
) -> tuple[LibraryObject, Job]:
    """Store the model file and queue its preparation. 422 for a bad name, unit, suffix,
    symmetry, an empty file or one whose content is not its format; 413 past
    ``max_bytes``; 409 when the name is taken; 507 when the storage is full.

    ``lookup`` opens a short read-only session for the name check made before the file is
    stored, so that ``session`` is used only for the insert (on SQLite its write lock is
    then not held while a large file is written). Without it ``session`` does both."""
    filename, source, units = upload.filename, upload.source, upload.units
    name = upload.name.strip()
    if not name:
        raise InvalidInput("name: the detector class name of the object")
    if (problem := jsondoc.text_problem(name)) is not None:
        raise InvalidInput(f"name: {problem}")
    if units not in UNITS:
        raise InvalidInput(f"units: {units!r} is not one of m, cm, mm")
    suffix = PurePosixPath(filename or "").suffix.lower()
    if suffix not in MODEL_SUFFIXES:
        raise InvalidInput(
            f"file: {filename!r} is not a model file ({', '.join(sorted(MODEL_SUFFIXES))})"
        )
    spec = parse_symmetry(upload.symmetry)
    with nullcontext(session) if lookup is None else lookup() as reader:
        _check_name_free(reader, name)
    object_id = new_id()
    key = f"objects/{object_id}/model{suffix}"
    try:
        blob = storage.write_stream(key, source, max_bytes=max_bytes)
    except OverflowError as exc:
        storage.delete_prefix(f"objects/{object_id}")
        raise PayloadTooLarge(f"file: larger than {max_bytes} bytes") from exc
    except OSError as exc:
        storage.delete_prefix(f"objects/{object_id}")
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):
            raise InsufficientStorage(
                "file: the server's storage is full; nothing was kept, try again later"
            ) from exc
        raise
    if blob.size_bytes == 0:
        storage.delete_prefix(f"objects/{object_id}")
        raise InvalidInput(f"file: {filename!r} is empty")
    with storage.open(key) as stored:
        problem = format_problem(suffix, stored.read(65536), blob.size_bytes)
    if problem is not None:
        storage.delete_prefix(f"objects/{object_id}")
        raise InvalidInput(f"file: {filename!r} is not a {suffix} model: {problem}")
    try:
        _check_name_free(session, name)  # again, in the writing transaction
    except Conflict:
        storage.delete_prefix(f"objects/{object_id}")
        raise
    obj = LibraryObject(
        id=object_id,
        name=name,
        units=units,
        symmetry_requested=spec,
        filename=PurePosixPath(filename).name,
        file_key=key,
        size_bytes=blob.size_bytes,
    )
    session.add(obj)
    session.flush()
    job = jobs.create(session, JobKind.object, TASK, object_id=object_id)
    return obj, job


def get(session: Session, object_id: str) -> LibraryObject:
    obj = session.get(LibraryObject, object_id)
    if obj is None or obj.deleted_at is not None:
        raise NotFound(f"object {object_id} not found")
    return obj


def list_live(session: Session) -> list[LibraryObject]:
    return list(
        session.scalars(
            select(LibraryObject)
            .where(LibraryObject.deleted_at.is_(None))
            .order_by(LibraryObject.name)
        ).all()
    )


def by_names(session: Session, names: list[str]) -> dict[str, LibraryObject]:
    rows = session.scalars(
        select(LibraryObject).where(
            LibraryObject.name.in_(names), LibraryObject.deleted_at.is_(None)
        )
    ).all()
    return {r.name: r for r in rows}


def delete(session: Session, object_id: str) -> LibraryObject:
    """Soft delete: history that refers to the object stays readable. A preparation job
    still queued is cancelled with it; a running one is asked to stop."""
    obj = get(session, object_id)
    obj.deleted_at = utcnow()
    live = [JobState.queued, JobState.running]
    active = session.scalars(
        select(Job.id).where(Job.object_id == object_id, Job.state.in_(live))
    ).all()
    for job_id in active:
        jobs.cancel(session, job_id)
    return obj


def latest_job(session: Session, object_id: str) -> Job | None:
    return session.scalar(
        select(Job).where(Job.object_id == object_id).order_by(Job.created_at.desc()).limit(1)
    )
