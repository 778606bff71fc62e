"""On-disk inputs of the compare stage (the command line's format).

A capture folder holds:
- ``cloud.ply``: the snapshot's point cloud, environment frame, metres (colours optional);
- ``cameras.json``: the one format (:mod:`app.formats.cameras`; what ``reconstruct``
  writes), intrinsics and ``poses`` (4×4 env_from_cam) by image name; only posed images
  count; distortion parameters are ignored (images are taken as undistorted);
- ``labels/<image stem>.txt``: YOLO detections (:mod:`app.formats.yolo`), ``class cx cy w h
  [conf]`` normalised;
- ``images/`` beside the labels folder (optional): the photos, by image name, read to check
  what each camera saw against the cloud's colours;
- ``classes.txt`` (optional here): one class name per line, line i = class id i;
- ``alignment.json`` (optional): ``{"residual_m": float}``.
Every function raises InputError naming the file (and line) at fault.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from app.formats import FormatError
from app.formats.cameras import (
    CamerasFile,
    from_reconstruction_images,
    is_reconstruction_images,
    read_cameras,
)
from app.formats.yolo import read_class_names, read_yolo
from workers.pipeline.compare.data import Camera, CaptureData, TwinInstance
from workers.pipeline.errors import InputError


def cameras_from_file(cameras: CamerasFile, where: str = "cameras.json") -> tuple[Camera, ...]:
    """The posed cameras of a cameras.json (images without a pose are skipped), sorted by
    name: K (3, 3) from the pinhole part of the params (distortion ignored: images are taken
    as undistorted) and ``cam_from_env`` the inverse of its ``env_from_cam``."""
    cams = []
    for name in sorted(cameras.poses):
        camera = cameras.camera_for(name)
        if camera is None:
            raise InputError(f"{where}: no intrinsics for image {name!r}")
        fx, fy, cx, cy = camera.pinhole
        k = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        env_from_cam = np.asarray(cameras.poses[name], dtype=np.float64)
        cam_from_env = np.asarray(np.linalg.inv(env_from_cam), dtype=np.float64)
        cams.append(Camera(name, k, camera.width, camera.height, cam_from_env, camera.distortion))
    return tuple(cams)


def read_cameras_file(path: Path) -> CamerasFile:
    """A cameras.json in the one format (:mod:`app.formats.cameras`), or as ``reconstruct``
    wrote it before (``{"images": ...}``, kept for stored snapshots); InputError naming the
    field otherwise."""
    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8-sig"))
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: cannot read JSON ({exc})") from exc
    try:
        if is_reconstruction_images(doc):
            return from_reconstruction_images(doc, str(path))
        return read_cameras(doc, str(path))
    except FormatError as exc:
        raise InputError(str(exc)) from exc


def load_cameras(path: Path) -> list[Camera]:
    """Cameras with poses from a cameras.json (images without a pose are skipped)."""
    return list(cameras_from_file(read_cameras_file(path), str(path)))


def load_labels(path: Path) -> NDArray[np.float64]:
    """(M, 6) rows ``class cx cy w h confidence`` of one YOLO label file
    (:mod:`app.formats.yolo`; confidence 1 when absent); InputError with the line number
    on a bad line."""
    try:
        with Path(path).open("rb") as fh:
            boxes = read_yolo(fh, str(path))
    except OSError as exc:
        raise InputError(f"{path}: cannot read labels ({exc})") from exc
    except FormatError as exc:
        raise InputError(str(exc)) from exc
    rows = [
        [b.class_id, b.cx, b.cy, b.w, b.h, 1.0 if b.confidence is None else b.confidence]
        for b in boxes
    ]
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


def load_capture(folder: Path, labels_dir: Path | None = None) -> CaptureData:
    """A :class:`CaptureData` from a capture folder (see module docstring); the YOLO labels
    from ``labels_dir`` when given (a reconstruct output folder has none: they stay with
    the capture's images), else ``folder/labels``."""
    points, colors = load_cloud(folder / "cloud.ply")
    cams = load_cameras(folder / "cameras.json") if (folder / "cameras.json").is_file() else []
    labels = folder / "labels" if labels_dir is None else labels_dir
    dets = {}
    for cam in cams:
        f = labels / (Path(cam.name).stem + ".txt")
        if f.is_file():
            dets[cam.name] = load_labels(f)
    residual = 0.0
    if (folder / "alignment.json").is_file():
        residual = float(json.loads((folder / "alignment.json").read_text())["residual_m"])
    photos = {c.name: labels.parent / "images" / c.name for c in cams}
    photos = {name: f for name, f in photos.items() if f.is_file()}
    return CaptureData(points, tuple(cams), dets, colors, residual, photos)


def read_photo(path: Path, camera: Camera, max_side: int) -> NDArray[np.float32] | None:
    """The photo of ``camera`` as (H, W, 3) RGB in [0, 1], undistorted with the camera's
    lens, read at a reduced size (a power of two, still ≥ ``max_side`` on its long side);
    None when the file cannot be read or is not the camera's size (then the caller goes
    without it)."""
    import cv2  # heavy: imported only when a photo is read

    long_side = max(camera.width, camera.height)
    factor = next((f for f in (8, 4, 2) if long_side / f >= max_side), 1)
    flags = {
        1: cv2.IMREAD_COLOR,
        2: cv2.IMREAD_REDUCED_COLOR_2,
        4: cv2.IMREAD_REDUCED_COLOR_4,
        8: cv2.IMREAD_REDUCED_COLOR_8,
    }
    img = cv2.imread(str(path), flags[factor])
    if img is None:
        return None
    w, h = round(camera.width / factor), round(camera.height / factor)
    if abs(img.shape[1] - w) > 1 or abs(img.shape[0] - h) > 1:
        return None
    if any(camera.distortion):
        k = camera.k.copy()
        k[:2] *= np.array([[img.shape[1] / camera.width], [img.shape[0] / camera.height]])
        img = cv2.undistort(img, k, np.asarray(camera.distortion))
    rgb: NDArray[np.float32] = img[:, :, ::-1].astype(np.float32) / np.float32(255.0)
    return rgb


def load_classes(path: Path) -> list[str]:
    """Class names, one per line (line i = detector class id i; :mod:`app.formats.yolo`),
    blank lines skipped."""
    try:
        with Path(path).open("rb") as fh:
            return [name for name in read_class_names(fh, str(path)) if name]
    except OSError as exc:
        raise InputError(f"{path}: cannot read classes ({exc})") from exc
    except FormatError as exc:
        raise InputError(str(exc)) from exc


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
