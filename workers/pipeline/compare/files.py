"""On-disk inputs of the compare stage (the command line's format).

A capture folder holds:
- ``cloud.ply``: the snapshot's point cloud, environment frame, metres (colours optional);
- ``cameras.json``: docs/contract.md's format, ``{"intrinsics": {"model", "width", "height",
  "params"}}`` or ``{"intrinsics_per_image": {name: {...}}}`` and ``{"poses": {name: 4×4
  env_from_cam}}``; models PINHOLE, SIMPLE_PINHOLE, SIMPLE_RADIAL, OPENCV (distortion
  parameters are ignored: images are taken as undistorted);
- ``labels/<image stem>.txt``: YOLO detections, ``class cx cy w h [conf]`` normalised;
- ``classes.txt`` (optional here): one class name per line, line i = class id i;
- ``alignment.json`` (optional): ``{"residual_m": float}``.
Every function raises InputError naming the file (and line) at fault.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from workers.pipeline.compare.data import Camera, CaptureData, TwinInstance
from workers.pipeline.errors import InputError, PipelineError
from workers.pipeline.geometry import invert_rigid


def intrinsics_matrix(spec: dict[str, Any], where: str) -> tuple[NDArray[np.float64], int, int]:
    """(K (3, 3), width, height) from a cameras.json intrinsics object."""
    try:
        model = str(spec["model"]).upper()
        w, h = int(spec["width"]), int(spec["height"])
        p = [float(x) for x in spec["params"]]
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{where}: intrinsics need model, width, height, params") from exc
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL") and len(p) >= 3:
        fx = fy = p[0]
        cx, cy = p[1], p[2]
    elif model in ("PINHOLE", "OPENCV") and len(p) >= 4:
        fx, fy, cx, cy = p[:4]
    else:
        raise InputError(f"{where}: unsupported camera model {model!r} with {len(p)} params")
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]), w, h


def load_cameras(path: Path) -> list[Camera]:
    """Cameras with poses from a cameras.json (images without a pose are skipped)."""
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: cannot read JSON ({exc})") from exc
    poses = doc.get("poses") or {}
    per_image = doc.get("intrinsics_per_image") or {}
    shared = doc.get("intrinsics")
    cams = []
    for name in sorted(poses):
        spec = per_image.get(name, shared)
        if spec is None:
            raise InputError(f"{path}: no intrinsics for image {name!r}")
        k, w, h = intrinsics_matrix(spec, f"{path} [{name}]")
        try:
            cam_from_env = invert_rigid(np.asarray(poses[name], dtype=np.float64))
            cams.append(Camera(name, k, w, h, cam_from_env))
        except (PipelineError, ValueError) as exc:
            raise InputError(f"{path} [{name}]: bad pose ({exc})") from exc
    return cams


def load_labels(path: Path) -> NDArray[np.float64]:
    """(M, 6) YOLO rows of one label file; InputError with the line number on a bad line."""
    rows = []
    for i, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        parts = line.split()
        try:
            vals = [float(x) for x in parts]
        except ValueError as exc:
            raise InputError(f"{path}:{i}: not numbers: {line!r}") from exc
        if len(vals) not in (5, 6) or vals[0] < 0 or vals[0] != int(vals[0]):
            raise InputError(f"{path}:{i}: expected 'class cx cy w h [conf]', got {line!r}")
        if not all(0.0 <= v <= 1.0 for v in vals[1:5]):
            raise InputError(f"{path}:{i}: coordinates must be normalised to 0..1")
        rows.append(vals if len(vals) == 6 else [*vals, 1.0])
    return np.array(rows, dtype=np.float64).reshape(-1, 6)


def load_cloud(path: Path) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    """(N, 3) points and (N, 3) colours in 0..1 (or None) from a PLY file."""
    import open3d as o3d  # heavy: imported only when a file is read

    if not path.is_file():
        raise InputError(f"{path}: missing point cloud")
    pcd = o3d.io.read_point_cloud(path)
    pts = np.asarray(pcd.points, dtype=np.float64)
    if len(pts) == 0:
        raise InputError(f"{path}: no points")
    colors = np.asarray(pcd.colors, dtype=np.float64) if pcd.has_colors() else None
    return pts, colors


def load_capture(folder: Path) -> CaptureData:
    """A :class:`CaptureData` from a capture folder (see module docstring)."""
    points, colors = load_cloud(folder / "cloud.ply")
    cams = load_cameras(folder / "cameras.json") if (folder / "cameras.json").is_file() else []
    labels = folder / "labels"
    dets = {}
    for cam in cams:
        f = labels / (Path(cam.name).stem + ".txt")
        if f.is_file():
            dets[cam.name] = load_labels(f)
    residual = 0.0
    if (folder / "alignment.json").is_file():
        residual = float(json.loads((folder / "alignment.json").read_text())["residual_m"])
    return CaptureData(points, tuple(cams), dets, colors, residual)


def load_classes(path: Path) -> list[str]:
    """Class names, one per line (line i = detector class id i)."""
    try:
        return [ln.strip() for ln in path.read_text().splitlines() if ln.strip()]
    except OSError as exc:
        raise InputError(f"{path}: cannot read classes ({exc})") from exc


def load_twin(path: Path) -> list[TwinInstance]:
    """Twin instances from ``[{"instance_id", "object", "pose": 4×4 env_from_object,
    "centroid"?: [x, y, z]}]`` (the ``objects`` of GET /environments/{id}/state)."""
    try:
        doc = json.loads(path.read_text())
        items = doc["objects"] if isinstance(doc, dict) else doc
        return [
            TwinInstance(
                str(o["instance_id"]),
                str(o["object"]),
                np.asarray(o["pose"], dtype=np.float64),
                None if o.get("centroid") is None else np.asarray(o["centroid"], dtype=float),
            )
            for o in items
        ]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputError(f"{path}: bad twin state ({exc})") from exc
