"""Prepare a library object once: load, convert units, sample, describe, detect symmetry.

``prepare_model(path, work_dir, options, units, symmetry)`` turns a mesh or point-cloud
file (.ply .obj .stl .glb .off .pcd) into a :class:`PreparedModel` — everything pose
estimation needs — and writes it under ``work_dir`` so that later jobs only call
:func:`load_prepared`. All coordinates are in the model's own frame (``object`` frame:
the frame ``env_from_object`` maps from), in metres after unit conversion.

Work-directory layout (version ``FORMAT_VERSION``)::

    work_dir/
      summary.json        name, source sha256, units, options, diameter_m, voxel_m,
                          centre_object, up_object, symmetry spec (and whether detected
                          or explicit), near_symmetries (4×4 lists), point counts, timings;
                          written last, so its presence means the directory is complete
      model.ply           (N, 3) sampled surface cloud with normals and colours (metres)
      model_down.ply      (M, 3) the same cloud voxel-downsampled at ``voxel_m``
      features.npy        (K, 6) float64 points and normals that carry the descriptors: the
                          downsampled cloud, then its part visible from each of
                          ``feature_views`` viewpoints (a scan sees one side; its FPFH
                          must not include the hidden side of a thin object)
      fpfh.npy            (K, 33) float32 FPFH descriptors of ``features.npy``

Re-running with the same source file, units, options and symmetry request returns the
stored result without recomputing it.
"""

from __future__ import annotations

import hashlib
import json
import time
import uuid
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from workers.pipeline.errors import InputError
from workers.pipeline.geometry import Points
from workers.pipeline.model.describe import (
    diameter_m,
    downsample_cloud,
    make_cloud,
    view_features,
)
from workers.pipeline.model.detect_symmetry import detect_symmetry, near_symmetries
from workers.pipeline.model.load import (
    file_sha256,
    load_surface,
)
from workers.pipeline.model.options import MODEL_PRESETS, ModelOptions
from workers.pipeline.model.symmetry_group import SymmetrySpec, spec_from_json, spec_to_json

FORMAT_VERSION = 4  # 4: texture colours read the right way up


@dataclass(frozen=True)
class PreparedModel:
    """A library object ready for registration (all in the object frame, metres).

    ``points``/``normals``: (N, 3) float64 surface samples and unit outward normals;
    ``colors``: (N, 3) float64 in [0, 1] or None; ``down_points``/``down_normals``: (M, 3)
    at ``voxel_m``; ``feature_points``/``feature_normals``: (K, 3) points carrying the
    ``fpfh`` (K, 33) descriptors (whole-model and per-view); ``centre_object``: (3,) centroid of the
    samples; ``up_object``: (3,) unit "up" of the object (model +z unless the file says
    otherwise) used to choose among symmetric poses and upside-down near-ties;
    ``symmetry``: see :mod:`workers.pipeline.model.symmetry_group`; ``near_symmetries``:
    4×4 rotations that almost map the object onto itself (tried explicitly by pose
    estimation).
    """

    name: str
    points: Points
    normals: Points
    colors: Points | None
    down_points: Points
    down_normals: Points
    down_colors: Points | None
    feature_points: Points
    feature_normals: Points
    fpfh: NDArray[np.float64]
    diameter_m: float
    voxel_m: float
    centre_object: NDArray[np.float64]
    up_object: NDArray[np.float64]
    symmetry: SymmetrySpec
    summary: dict[str, Any]
    near_symmetries: tuple[NDArray[np.float64], ...] = ()


def _request_key(sha: str, units: str, options: ModelOptions, symmetry: SymmetrySpec | None) -> str:
    blob = json.dumps(
        {
            "v": FORMAT_VERSION,
            "sha": sha,
            "units": units,
            "options": asdict(options),
            "symmetry": None if symmetry is None else spec_to_json(symmetry),
        },
        sort_keys=True,
    )
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def prepare_model(
    path: Path,
    work_dir: Path,
    options: ModelOptions = MODEL_PRESETS["default"],
    units: str = "m",
    symmetry: SymmetrySpec | None = None,
    name: str | None = None,
) -> PreparedModel:
    """Load ``path`` (units ``units``), sample, describe and save it under ``work_dir``.

    ``symmetry`` None means detect it; an explicit spec is validated and kept. Returns the
    prepared model (object frame, metres). Resumes: when ``work_dir/summary.json`` was
    written for the same file, units, options and symmetry request, loads it instead.
    Raises InputError for unusable files, units or symmetry specs.
    """
    path = Path(path)
    work_dir = Path(work_dir)
    if not path.is_file():
        raise InputError(f"{path.name}: model file not found")
    sha = file_sha256(path)
    key = _request_key(sha, units, options, symmetry)
    summary_path = work_dir / "summary.json"
    if summary_path.is_file():
        try:
            if json.loads(summary_path.read_text()).get("request_key") == key:
                return load_prepared(work_dir)
        except (ValueError, InputError):
            pass
    t0 = time.perf_counter()
    points, normals, colors = load_surface(path, options, units)
    t_load = time.perf_counter() - t0
    diam = diameter_m(points)
    if not np.isfinite(diam) or diam <= 1e-6:
        raise InputError(f"{path.name}: the model has no extent (diameter {diam:g} m)")
    if diam > 100.0:
        raise InputError(
            f"{path.name}: diameter {diam:g} m after conversion from {units!r} — wrong units?"
        )
    voxel = diam / options.voxel_divisor
    t1 = time.perf_counter()
    d_pts, d_nrm, d_col = downsample_cloud(points, normals, colors, voxel)
    f_pts, f_nrm, fpfh = view_features(points, normals, d_pts, d_nrm, voxel, options)
    t_feat = time.perf_counter() - t1
    t2 = time.perf_counter()
    spec = symmetry if symmetry is not None else detect_symmetry(points, colors, options.symmetry)
    near = near_symmetries(points, spec, options.symmetry)
    t_sym = time.perf_counter() - t2
    centre = points.mean(axis=0)
    up = np.array([0.0, 0.0, 1.0])
    summary: dict[str, Any] = {
        "format_version": FORMAT_VERSION,
        "request_key": key,
        "name": name or (path.parent.name if path.stem == "textured" else path.stem),
        "source": path.name,
        "sourcefile_sha256": sha,
        "units": units,
        "options": asdict(options),
        "diameter_m": diam,
        "voxel_m": voxel,
        "centre_object": centre.tolist(),
        "up_object": up.tolist(),
        "n_points": len(points),
        "n_down": len(d_pts),
        "n_features": len(f_pts),
        "has_colors": colors is not None,
        "symmetry": spec_to_json(spec),
        "near_symmetries": [np.round(m, 9).tolist() for m in near],
        "symmetry_source": "explicit" if symmetry is not None else "detected",
        "timings_s": {"load_sample": t_load, "features": t_feat, "symmetry": t_sym},
    }
    work_dir.mkdir(parents=True, exist_ok=True)
    o3d.io.write_point_cloud(work_dir / "model.ply", make_cloud(points, normals, colors))
    o3d.io.write_point_cloud(work_dir / "model_down.ply", make_cloud(d_pts, d_nrm, d_col))
    np.save(work_dir / "features.npy", np.hstack([f_pts, f_nrm]))
    np.save(work_dir / "fpfh.npy", fpfh.astype(np.float32))
    # a name of its own: two workers preparing the same model must not share a temporary file
    tmp = summary_path.with_name(f"summary.json.{uuid.uuid4().hex}.tmp")
    tmp.write_text(json.dumps(summary, indent=2))
    tmp.replace(summary_path)  # written last: its presence means the directory is complete
    return load_prepared(work_dir)


def load_prepared(work_dir: Path) -> PreparedModel:
    """Load a model written by :func:`prepare_model`; InputError if incomplete or stale."""
    work_dir = Path(work_dir)
    summary_path = work_dir / "summary.json"
    if not summary_path.is_file():
        raise InputError(f"{work_dir}: no prepared model (summary.json missing)")
    try:
        summary = json.loads(summary_path.read_text())
    except ValueError as exc:
        raise InputError(f"{summary_path}: unreadable summary ({exc})") from exc
    if summary.get("format_version") != FORMAT_VERSION:
        raise InputError(f"{work_dir}: prepared with format {summary.get('format_version')}")
    full = o3d.io.read_point_cloud(work_dir / "model.ply")
    down = o3d.io.read_point_cloud(work_dir / "model_down.ply")
    fpfh_path = work_dir / "fpfh.npy"
    feat_path = work_dir / "features.npy"
    if (
        len(full.points) == 0
        or len(down.points) == 0
        or not fpfh_path.is_file()
        or not feat_path.is_file()
    ):
        raise InputError(f"{work_dir}: prepared model files are missing or empty")
    fpfh = np.load(fpfh_path).astype(np.float64)
    feat = np.load(feat_path).astype(np.float64)
    if feat.ndim != 2 or feat.shape[1] != 6 or fpfh.shape != (len(feat), 33):
        raise InputError(
            f"{work_dir}: features.npy {feat.shape} and fpfh.npy {fpfh.shape} disagree"
        )
    has_col = bool(summary.get("has_colors"))
    return PreparedModel(
        name=str(summary["name"]),
        points=np.asarray(full.points).copy(),
        normals=np.asarray(full.normals).copy(),
        colors=np.asarray(full.colors).copy() if has_col else None,
        down_points=np.asarray(down.points).copy(),
        down_normals=np.asarray(down.normals).copy(),
        down_colors=np.asarray(down.colors).copy() if has_col else None,
        feature_points=feat[:, :3].copy(),
        feature_normals=feat[:, 3:].copy(),
        fpfh=fpfh,
        diameter_m=float(summary["diameter_m"]),
        voxel_m=float(summary["voxel_m"]),
        centre_object=np.asarray(summary["centre_object"], dtype=np.float64),
        up_object=np.asarray(summary["up_object"], dtype=np.float64),
        symmetry=spec_from_json(summary["symmetry"]),
        near_symmetries=tuple(
            np.asarray(m, dtype=np.float64) for m in summary.get("near_symmetries", [])
        ),
        summary=summary,
    )


def with_symmetry(model: PreparedModel, spec: SymmetrySpec) -> PreparedModel:
    """The same prepared model with another symmetry spec (not written to disk)."""
    return replace(model, symmetry=spec)
