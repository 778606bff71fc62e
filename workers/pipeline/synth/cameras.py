"""Pinhole intrinsics and the camera path of one capture (OpenCV camera axes)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from app.formats.cameras import Camera
from workers.pipeline.errors import InputError
from workers.pipeline.geometry import Mat4, make_rigid
from workers.pipeline.synth.options import CameraOptions, EffectsOptions, PathOptions


def intrinsics_matrix(camera: CameraOptions) -> NDArray[np.float64]:
    """(3, 3) K with fx = fy = ``focal_px`` and the principal point at the image centre.

    Pixel centres sit at integer coordinates (OpenCV), so the centre is ((W−1)/2, (H−1)/2).
    """
    cx, cy = (camera.width - 1) / 2.0, (camera.height - 1) / 2.0
    return np.asarray([[camera.focal_px, 0.0, cx], [0.0, camera.focal_px, cy], [0.0, 0.0, 1.0]])


def distortion_coeffs(effects: EffectsOptions | None) -> tuple[float, ...] | None:
    """OpenCV's (k1, k2, p1, p2, k3) of the lens in ``effects``; None for a pinhole.
    InputError for an unknown model."""
    if effects is None or effects.distortion is None:
        return None
    if effects.distortion == "OPENCV":
        return (effects.k1, effects.k2, effects.p1, effects.p2, 0.0)
    if effects.distortion == "SIMPLE_RADIAL":
        return (effects.k1, 0.0, 0.0, 0.0, 0.0)
    raise InputError(
        f"unknown distortion model {effects.distortion!r}; choose 'OPENCV' or 'SIMPLE_RADIAL'"
    )


def cameras_json_intrinsics(camera: CameraOptions, effects: EffectsOptions | None = None) -> Camera:
    """The shared intrinsics of a capture's cameras.json: PINHOLE [fx, fy, cx, cy], or the
    lens of ``effects``: OPENCV [fx, fy, cx, cy, k1, k2, p1, p2] or SIMPLE_RADIAL
    [f, cx, cy, k1]."""
    k = intrinsics_matrix(camera)
    fx, fy, cx, cy = float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2])
    distortion = distortion_coeffs(effects)
    if distortion is None or effects is None:
        return Camera("PINHOLE", camera.width, camera.height, (fx, fy, cx, cy))
    if effects.distortion == "SIMPLE_RADIAL":
        return Camera("SIMPLE_RADIAL", camera.width, camera.height, (fx, cx, cy, effects.k1))
    return Camera("OPENCV", camera.width, camera.height, (fx, fy, cx, cy, *distortion[:4]))


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
    if path.rings_m:
        return _ring_path(path, rng)
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


def _ring_path(path: PathOptions, rng: np.random.Generator) -> list[Mat4]:
    """``env_from_cam`` for views taking the rings of ``path.rings_m`` (radius, height) in
    turn, each ring an even sweep of ``arc_deg`` from its own random phase, with the radius
    and target jitter of ``path`` and ±5 cm of height jitter."""
    rings = path.rings_m
    if any(r <= 0.0 or h <= 0.0 for r, h in rings):
        raise InputError(f"rings need positive radius and height, got {rings}")
    phases = rng.uniform(0.0, 2.0 * np.pi, len(rings))
    counts = [len(range(i, path.n_views, len(rings))) for i in range(len(rings))]
    out = []
    for k in range(path.n_views):
        ring = k % len(rings)
        radius_m, height_m = rings[ring]
        theta = phases[ring] + np.radians(path.arc_deg) * (k // len(rings)) / counts[ring]
        radius = radius_m + path.radius_jitter_m * rng.uniform(-1.0, 1.0)
        height = height_m + 0.05 * rng.uniform(-1.0, 1.0)
        eye = np.asarray([radius * np.cos(theta), radius * np.sin(theta), height])
        target = np.asarray([0.0, 0.0, 0.05]) + rng.uniform(-1.0, 1.0, 3) * path.target_jitter_m
        out.append(look_at(eye, target))
    return out
