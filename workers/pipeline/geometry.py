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
Vec3 = NDArray[np.float64] | tuple[float, float, float]


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
    # A contiguous copy of the transposed rotation: BLAS takes a much slower path on a
    # transposed view (measured 100× on this machine for 480k points).
    return p @ np.ascontiguousarray(m[:3, :3].T) + m[:3, 3]


def rotation_angle_deg(rotation: ArrayLike) -> float:
    """Geodesic angle of a (3, 3) rotation matrix, degrees in [0, 180]."""
    r = np.asarray(rotation, dtype=np.float64)
    if r.shape != (3, 3):
        raise ShapeError(f"rotation must be 3×3, got {r.shape}")
    cos = (np.trace(r) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def skew(vector: ArrayLike) -> NDArray[np.float64]:
    """(3, 3) cross-product matrix ``[v]×`` of a (3,) vector: ``skew(v) @ w == cross(v, w)``."""
    v = np.asarray(vector, dtype=np.float64).reshape(3)
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def perpendicular_pair(unit_axis: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Two (3,) unit vectors ``u``, ``v`` with ``(u, v, unit_axis)`` right-handed and
    orthonormal, for a (3,) axis of length 1 (not normalised here)."""
    a = np.asarray(unit_axis, dtype=np.float64).reshape(3)
    u = _cross3(a, (1.0, 0.0, 0.0) if abs(a[0]) < 0.9 else (0.0, 1.0, 0.0))
    u /= np.linalg.norm(u)
    return u, _cross3(a, u)


def _cross3(a: Vec3, b: Vec3) -> NDArray[np.float64]:
    """``np.cross`` of two (3,) vectors, the same arithmetic without its per-call overhead
    (a pose fit takes tens of thousands)."""
    a0, a1, a2 = a
    b0, b1, b2 = b
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], dtype=np.float64)


def rotation_about_unit_axis(unit_axis: ArrayLike, angle_rad: float) -> NDArray[np.float64]:
    """(3, 3) rotation by ``angle_rad`` (right-handed) about a (3,) axis of length 1
    (Rodrigues: ``I + sin θ K + (1 − cos θ) K²``, ``K = skew(axis)``); not normalised here."""
    k = skew(unit_axis)
    out: NDArray[np.float64] = (
        np.eye(3) + np.sin(angle_rad) * k + (1.0 - np.cos(angle_rad)) * (k @ k)
    )
    return out


def rotation_onto(from_unit: ArrayLike, to_unit: ArrayLike) -> NDArray[np.float64]:
    """(3, 3) smallest rotation turning the (3,) unit vector ``from_unit`` onto ``to_unit``
    (opposite vectors: 180° about an axis perpendicular to both)."""
    a = np.asarray(from_unit, dtype=np.float64)
    b = np.asarray(to_unit, dtype=np.float64)
    axis = np.cross(a, b)
    sin, cos = float(np.linalg.norm(axis)), float(a @ b)
    if sin < 1e-12:
        return np.eye(3) if cos > 0 else rotation_about_unit_axis(perpendicular_pair(a)[0], np.pi)
    return rotation_about_unit_axis(axis / sin, float(np.arctan2(sin, cos)))


def axis_angle_matrix(axis: ArrayLike, angle_rad: float) -> NDArray[np.float64]:
    """(3, 3) rotation by ``angle_rad`` (right-handed) about the (3,) ``axis`` (any length > 0);
    ShapeError for a wrong shape or a zero or non-finite axis."""
    a = np.asarray(axis, dtype=np.float64).reshape(-1)
    if a.shape != (3,):
        raise ShapeError(f"axis must be (3,), got {a.shape}")
    norm = float(np.linalg.norm(a))
    if norm <= 0 or not np.isfinite(norm):
        raise ShapeError("axis must be a finite non-zero vector")
    return rotation_about_unit_axis(a / norm, angle_rad)


def rotation_from_rotvec(rotvec: ArrayLike) -> NDArray[np.float64]:
    """(3, 3) rotation of a (3,) rotation vector (axis × angle in radians); the identity
    below 1e-12 rad."""
    w = np.asarray(rotvec, dtype=np.float64).reshape(3)
    angle = float(np.linalg.norm(w))
    if angle < 1e-12:
        return np.eye(3)
    return rotation_about_unit_axis(w / angle, angle)


def pose_error(estimated_a_from_b: ArrayLike, true_a_from_b: ArrayLike) -> tuple[float, float]:
    """(translation error in metres, geodesic rotation error in degrees) between two poses."""
    est = as_mat4(estimated_a_from_b, "estimated")
    true = as_mat4(true_a_from_b, "true")
    dt = float(np.linalg.norm(est[:3, 3] - true[:3, 3]))
    return dt, rotation_angle_deg(est[:3, :3].T @ true[:3, :3])


def umeyama_similarity(src_points: ArrayLike, dst_points: ArrayLike) -> tuple[Mat4, float]:
    """Least-squares similarity ``dst_from_src`` (Umeyama 1991) with its scale.

    ``src_points`` and ``dst_points`` are matching (N, 3) arrays, N ≥ 3 and not collinear.
    Returns the 4×4 ``dst_from_src = [s·R | t]`` (its upper-left block is scale × rotation)
    and the scale ``s``. Raises ShapeError on mismatched shapes or degenerate input.
    """
    src = as_points(src_points, "src_points")
    dst = as_points(dst_points, "dst_points")
    if src.shape != dst.shape or src.shape[0] < 3:
        raise ShapeError(f"need matching (N≥3, 3) arrays, got {src.shape} and {dst.shape}")
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    xs, xd = src - mu_s, dst - mu_d
    var_s = float((xs**2).sum() / len(src))
    if var_s <= 0.0:
        raise ShapeError("source points are all identical")
    cov = xd.T @ xs / len(src)
    u, d, vt = np.linalg.svd(cov)
    if d[1] <= 1e-12 * max(d[0], 1e-300):
        raise ShapeError("points are collinear; similarity is not determined")
    sign = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2, 2] = -1.0
    rot = u @ sign @ vt
    scale = float(np.trace(np.diag(d) @ sign) / var_s)
    out = np.eye(4)
    out[:3, :3] = scale * rot
    out[:3, 3] = mu_d - scale * rot @ mu_s
    return out, scale


def project_points(
    k_matrix: ArrayLike, cam_from_world: ArrayLike, points_world: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Pinhole projection of (N, 3) world points: returns ((N, 2) pixels, (N,) depths in m).

    ``k_matrix`` is the (3, 3) intrinsic matrix; ``cam_from_world`` a 4×4 rigid transform;
    OpenCV axes (depth = camera z). Points at depth ≤ 0 get non-finite pixels.
    """
    k = np.asarray(k_matrix, dtype=np.float64)
    if k.shape != (3, 3):
        raise ShapeError(f"k_matrix must be 3×3, got {k.shape}")
    p_cam = transform_points(cam_from_world, points_world)
    z = p_cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (p_cam[:, :2] / np.where(z > 0, z, np.nan)[:, None]) @ k[:2, :2].T + k[:2, 2]
    return uv, z


def triangulate_dlt(projections: ArrayLike, pixels: ArrayLike) -> NDArray[np.float64]:
    """Linear multi-view triangulation (DLT) of one point seen in V ≥ 2 views.

    ``projections`` is (V, 3, 4) ``K @ cam_from_world[:3]``; ``pixels`` is (V, 2).
    Returns the (3,) point in the world frame. Raises ShapeError on bad shapes.
    """
    p = np.asarray(projections, dtype=np.float64)
    x = np.asarray(pixels, dtype=np.float64)
    if p.ndim != 3 or p.shape[1:] != (3, 4) or x.shape != (p.shape[0], 2) or p.shape[0] < 2:
        raise ShapeError(f"need (V≥2, 3, 4) projections, (V, 2) pixels; got {p.shape}, {x.shape}")
    rows = np.concatenate([x[:, :1] * p[:, 2] - p[:, 0], x[:, 1:] * p[:, 2] - p[:, 1]], axis=0)
    rows /= np.linalg.norm(rows, axis=1, keepdims=True)
    _, _, vt = np.linalg.svd(rows)
    h = vt[-1]
    return np.asarray(h[:3] / h[3], dtype=np.float64)


def rounded_rigid(a_from_b: Mat4, decimals: int) -> Mat4:
    """``a_from_b`` rounded to ``decimals`` and made a rotation again (Gram-Schmidt in
    element-wise arithmetic, so that equal inputs give bit-identical outputs)."""
    r = np.round(a_from_b[:3, :3], decimals)
    x = r[:, 0] / np.sqrt((r[:, 0] ** 2).sum())
    y = r[:, 1] - (x * r[:, 1]).sum() * x
    y = y / np.sqrt((y**2).sum())
    return make_rigid(np.column_stack([x, y, np.cross(x, y)]), np.round(a_from_b[:3, 3], decimals))
