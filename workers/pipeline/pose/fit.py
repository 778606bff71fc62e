"""Fitting primitives shared by the pose steps: point-to-plane ICP onto a scene target,
the truncated-quadratic score, and the exclusion penalty for where an object cannot be.

All points are (N, 3) float64 metres; poses are 4×4 ``env_from_object``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from workers.pipeline.compare.visibility import DepthMap, seen_empty_counts
from workers.pipeline.geometry import (
    Mat4,
    Points,
    make_rigid,
    rotation_from_rotvec,
    transform_points,
)


def normalised(a: Points) -> Points:
    """(N, 3) rows scaled to unit length (zero rows stay near zero)."""
    out: Points = a / np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-12)
    return out


class Target:
    """A scene cloud with unit normals and a KD-tree built once for every ICP run."""

    def __init__(self, pcd: o3d.geometry.PointCloud) -> None:
        self.points = np.asarray(pcd.points, dtype=np.float64).copy()
        self.normals = normalised(np.asarray(pcd.normals, dtype=np.float64))
        self.colors = np.asarray(pcd.colors, dtype=np.float64).copy() if pcd.has_colors() else None
        self.tree = cKDTree(self.points)


def icp_point_to_plane(
    src: Points, src_normals: Points, target: Target, init: Mat4, dist: float, iters: int
) -> Mat4:
    """Point-to-plane ICP of (N, 3) object points onto ``target``; returns env_from_object.

    Gauss-Newton on the linearised point-to-plane residual; pairs farther than ``dist`` or
    whose normals differ by more than 60° are ignored (a can's hidden bottom must not pair
    with the table under it). Stops when the update is below 1e-5 rad and 1e-4 ``dist``.
    """
    pose = init.copy()
    for _ in range(iters):
        p = src @ pose[:3, :3].T + pose[:3, 3]
        d, idx = target.tree.query(p, distance_upper_bound=dist)
        ok = np.isfinite(d)
        ok[ok] &= (
            np.einsum("ij,ij->i", src_normals[ok] @ pose[:3, :3].T, target.normals[idx[ok]]) > 0.5
        )
        if ok.sum() < 6:
            break
        p, q, n = p[ok], target.points[idx[ok]], target.normals[idx[ok]]
        r = np.einsum("ij,ij->i", p - q, n)
        jac = np.hstack([np.cross(p, n), n])
        h = jac.T @ jac
        try:
            x = np.linalg.solve(h + 1e-12 * np.eye(6), -jac.T @ r)
        except np.linalg.LinAlgError:
            break
        step = np.eye(4)
        step[:3, :3] = rotation_from_rotvec(x[:3])
        step[:3, 3] = x[3:]
        pose = step @ pose
        if np.linalg.norm(x[:3]) < 1e-5 and np.linalg.norm(x[3:]) < 1e-4 * dist:
            break
    return pose


def truncated_score(tree: cKDTree, points: Points, tau: float) -> float:
    """Mean of ``max(0, 1 − (d/τ)²)`` over (N, 3) points, ``d`` the distance to the scene."""
    d, _ = tree.query(points, distance_upper_bound=tau)
    d = np.where(np.isfinite(d), d, tau)
    return float(np.mean(np.clip(1.0 - (d / tau) ** 2, 0.0, None)))


def rounded_rigid(a_from_b: Mat4, decimals: int) -> Mat4:
    """``a_from_b`` rounded to ``decimals`` and made a rotation again (Gram-Schmidt in
    element-wise arithmetic, so that equal inputs give bit-identical outputs)."""
    r = np.round(a_from_b[:3, :3], decimals)
    x = r[:, 0] / np.sqrt((r[:, 0] ** 2).sum())
    y = r[:, 1] - (x * r[:, 1]).sum() * x
    y = y / np.sqrt((y**2).sum())
    return make_rigid(np.column_stack([x, y, np.cross(x, y)]), np.round(a_from_b[:3, 3], decimals))


def exclusion_factor(
    posed: Points,
    support: NDArray[np.float64] | None,
    free_space: Sequence[DepthMap],
    band: float,
) -> float:
    """1 − 3 × the share of (N, 3) posed model points where the object cannot be, at least
    0: more than ``band`` below the support plane (an object does not sink into the floor
    it stands on) or more than ``band`` in front of the surface a camera of the capture saw
    behind them (it does not fill space the cameras saw through: a hammer turned over
    about its handle puts its claw there)."""
    cannot = np.zeros(len(posed), dtype=bool)
    if support is not None:
        cannot |= posed @ support[:3] + support[3] < -band
    if free_space:
        cannot[~cannot] = seen_empty_counts(posed[~cannot], free_space, band) > 0
    return max(0.0, 1.0 - 3.0 * float(np.mean(cannot)))


def out_of_support(
    env_from_object: Mat4,
    model_points: Points,
    support: NDArray[np.float64] | None,
    on_support: Points,
    max_sink_m: float,
    clearance_m: float,
) -> Mat4:
    """The pose moved along the support plane's normal until its lowest (N, 3) model point
    (object frame) touches the plane, when it has sunk into it by at most ``max_sink_m``
    (metres; deeper, or above the plane: unchanged) and the plane reaches beyond the object:
    at least 30 of the (M, 3) scene points ``on_support`` lie more than ``clearance_m`` from
    the posed model (an object's own flat face is no floor). Stereo rounds an object's top
    edges down, so ICP onto a reconstruction tends to sink the pose."""
    if support is None or max_sink_m <= 0 or len(on_support) < 30:
        return env_from_object
    posed = transform_points(env_from_object, model_points)
    lowest = float(np.min(posed @ support[:3])) + float(support[3])
    if not -max_sink_m <= lowest < 0.0:
        return env_from_object
    d, _ = cKDTree(posed).query(on_support, distance_upper_bound=clearance_m)
    if int(np.count_nonzero(~np.isfinite(d))) < 30:
        return env_from_object
    out = env_from_object.copy()
    out[:3, 3] -= lowest * support[:3]
    return out
