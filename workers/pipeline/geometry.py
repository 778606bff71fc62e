"""Small rigid-geometry helpers shared by every stage.

Conventions: 4×4 float64 homogeneous matrices, metres, named ``dst_from_src``;
compose left to right (``a_from_c = a_from_b @ b_from_c``); camera axes are OpenCV's
(x right, y down, z forward).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from workers.pipeline.errors import ShapeError

Mat4 = NDArray[np.float64]
Points = NDArray[np.float64]


def as_mat4(matrix: ArrayLike, name: str = "matrix") -> Mat4:
    """Return ``matrix`` as a (4, 4) float64 array; raise ShapeError otherwise."""
    out = np.asarray(matrix, dtype=np.float64)
    if out.shape != (4, 4):
        raise ShapeError(f"{name} must be 4×4, got shape {out.shape}")
    if not np.all(np.isfinite(out)):
        raise ShapeError(f"{name} contains non-finite values")
    return out


def as_points(points: ArrayLike, name: str = "points") -> Points:
    """Return ``points`` as an (N, 3) float64 array; raise ShapeError otherwise."""
    out = np.asarray(points, dtype=np.float64)
    if out.ndim != 2 or out.shape[1] != 3:
        raise ShapeError(f"{name} must be (N, 3), got shape {out.shape}")
    return out


def make_rigid(rotation: ArrayLike, translation_m: ArrayLike) -> Mat4:
    """Build a 4×4 rigid transform from a (3, 3) rotation and a (3,) translation in metres."""
    r = np.asarray(rotation, dtype=np.float64)
    t = np.asarray(translation_m, dtype=np.float64).reshape(-1)
    if r.shape != (3, 3) or t.shape != (3,):
        raise ShapeError(f"rotation must be 3×3 and translation (3,), got {r.shape} and {t.shape}")
    out = np.eye(4)
    out[:3, :3] = r
    out[:3, 3] = t
    return out


def invert_rigid(a_from_b: ArrayLike) -> Mat4:
    """Inverse of a rigid (or similarity-free) 4×4 transform: returns ``b_from_a``."""
    m = as_mat4(a_from_b, "a_from_b")
    r = m[:3, :3]
    out = np.eye(4)
    out[:3, :3] = r.T
    out[:3, 3] = -r.T @ m[:3, 3]
    return out


def transform_points(a_from_b: ArrayLike, points_b: ArrayLike) -> Points:
    """Map (N, 3) points from frame b to frame a with a 4×4 ``a_from_b``."""
    m = as_mat4(a_from_b, "a_from_b")
    p = as_points(points_b, "points_b")
    return p @ m[:3, :3].T + m[:3, 3]


def rotation_angle_deg(rotation: ArrayLike) -> float:
    """Geodesic angle of a (3, 3) rotation matrix, degrees in [0, 180]."""
    r = np.asarray(rotation, dtype=np.float64)
    if r.shape != (3, 3):
        raise ShapeError(f"rotation must be 3×3, got {r.shape}")
    cos = (np.trace(r) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def pose_error(estimated_a_from_b: ArrayLike, true_a_from_b: ArrayLike) -> tuple[float, float]:
    """(translation error in metres, geodesic rotation error in degrees) between two poses."""
    est = as_mat4(estimated_a_from_b, "estimated")
    true = as_mat4(true_a_from_b, "true")
    dt = float(np.linalg.norm(est[:3, 3] - true[:3, 3]))
    return dt, rotation_angle_deg(est[:3, :3].T @ true[:3, :3])
