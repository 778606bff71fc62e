"""Pinhole intrinsics and the camera path of one capture (OpenCV camera axes)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from app.formats.cameras import Camera
from workers.pipeline.errors import InputError
from workers.pipeline.geometry import Mat4, make_rigid
from workers.pipeline.synth.options import CameraOptions, PathOptions


def intrinsics_matrix(camera: CameraOptions) -> NDArray[np.float64]:
    """(3, 3) K with fx = fy = ``focal_px`` and the principal point at the image centre.

    Pixel centres sit at integer coordinates (OpenCV), so the centre is ((W−1)/2, (H−1)/2).
    """
    cx, cy = (camera.width - 1) / 2.0, (camera.height - 1) / 2.0
    return np.asarray([[camera.focal_px, 0.0, cx], [0.0, camera.focal_px, cy], [0.0, 0.0, 1.0]])


def cameras_json_intrinsics(camera: CameraOptions) -> Camera:
    """The shared intrinsics of a capture's cameras.json: PINHOLE [fx, fy, cx, cy]."""
    k = intrinsics_matrix(camera)
    params = (float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]))
    return Camera("PINHOLE", camera.width, camera.height, params)


def look_at(eye_env: NDArray[np.float64], target_env: NDArray[np.float64]) -> Mat4:
    """``env_from_cam`` of a camera at ``eye_env`` looking at ``target_env`` (env z is up).

    Camera axes are OpenCV's: x right, y down, z forward.
    """
    forward = target_env - eye_env
    norm = float(np.linalg.norm(forward))
    if norm < 1e-9:
        raise InputError("camera eye and target coincide")
    forward = forward / norm
    right = np.cross(forward, [0.0, 0.0, 1.0])
    if float(np.linalg.norm(right)) < 1e-6:
        raise InputError("camera looks straight up or down; the look-at is undefined")
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    return make_rigid(np.stack([right, down, forward], axis=1), eye_env)


def camera_path(path: PathOptions, rng: np.random.Generator) -> list[Mat4]:
    """``env_from_cam`` for ``path.n_views`` views on a jittered ring around the origin.

    The random phase, radius and height jitter come from ``rng``, so each capture (its own
    generator) walks a different path.
    """
    if path.n_views < 1:
        raise InputError(f"n_views must be positive, got {path.n_views}")
    phase = rng.uniform(0.0, 2.0 * np.pi)
    wave_phase = rng.uniform(0.0, 2.0 * np.pi)
    mid = (path.height_min_m + path.height_max_m) / 2.0
    amp = (path.height_max_m - path.height_min_m) / 2.0
    out = []
    for k in range(path.n_views):
        theta = phase + np.radians(path.arc_deg) * k / path.n_views
        radius = path.radius_m + path.radius_jitter_m * rng.uniform(-1.0, 1.0)
        height = mid + amp * np.sin(path.height_waves * theta + wave_phase)
        height += 0.1 * amp * rng.uniform(-1.0, 1.0)
        eye = np.asarray([radius * np.cos(theta), radius * np.sin(theta), height])
        target = np.asarray([0.0, 0.0, 0.05]) + rng.uniform(-1.0, 1.0, 3) * path.target_jitter_m
        out.append(look_at(eye, target))
    return out
