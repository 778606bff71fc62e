"""Fitting primitives shared by the pose steps: point-to-plane ICP onto a scene target,
the truncated-quadratic score, and the exclusion penalty for where an object cannot be.

All points are (N, 3) float64 metres; poses are 4×4 ``env_from_object``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from scipy.spatial import ConvexHull, QhullError, cKDTree

from workers.pipeline.compare.visibility import DepthMap, depth_votes
from workers.pipeline.geometry import (
    Mat4,
    Points,
    perpendicular_pair,
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


class ModelSurface:
    """The model's (N, 3) surface samples and unit normals (object frame, metres) with a
    KD-tree, built once: the target of :func:`fit_scene_to_model`."""

    def __init__(self, points: Points, normals: Points) -> None:
        self.points = np.asarray(points, dtype=np.float64)
        self.normals = normalised(np.asarray(normals, dtype=np.float64))
        self.tree = cKDTree(self.points)


def _tukey_step(
    surface: ModelSurface,
    scene: Points,
    pose: Mat4,
    reach_m: float,
    sigma_floor_m: float,
    free: NDArray[np.float64],
) -> tuple[NDArray[np.float64] | None, float, NDArray[np.float64]]:
    """One Gauss-Newton step of :func:`fit_scene_to_model` within the span of the (6, F)
    ``free`` directions: (6,) [rotation vector, translation] to left-multiply (None when
    < 10 pairs), the Tukey width used (metres) and the (M,) weights of the scene points."""
    rot, t = pose[:3, :3], pose[:3, 3]
    d, idx = surface.tree.query((scene - t) @ rot, distance_upper_bound=reach_m)
    ok = np.isfinite(d)
    weights = np.zeros(len(scene))
    if ok.sum() < 10:
        return None, reach_m, weights
    p = surface.points[idx[ok]] @ rot.T + t
    n = surface.normals[idx[ok]] @ rot.T
    r = np.einsum("ij,ij->i", p - scene[ok], n)
    width = min(4.685 * max(1.4826 * float(np.median(np.abs(r))), sigma_floor_m), reach_m)
    w = np.where(np.abs(r) < width, (1.0 - (r / width) ** 2) ** 2, 0.0)
    weights[ok] = w
    jac = np.hstack([np.cross(p, n), n]) * np.sqrt(w)[:, None] @ free
    try:
        y = np.linalg.solve(jac.T @ jac + 1e-12 * np.eye(free.shape[1]), -jac.T @ (r * np.sqrt(w)))
    except np.linalg.LinAlgError:
        return None, width, weights
    return free @ y, width, weights


def _plane_motions(normal: NDArray[np.float64]) -> NDArray[np.float64]:
    """(6, 3) motions of a rigid body on a plane of unit ``normal``: the turn about it and
    the two shifts across it, as [rotation vector, translation] columns."""
    n = normalised(np.asarray(normal, dtype=np.float64)[None, :])[0]
    u, v = np.linalg.svd(np.eye(3) - np.outer(n, n))[0][:, :2].T
    free = np.zeros((6, 3))
    free[:3, 0], free[3:, 1], free[3:, 2] = n, u, v
    return free


def fit_scene_to_model(
    surface: ModelSurface,
    scene: Points,
    init: Mat4,
    reach_m: float,
    iters: int,
    sigma_floor_m: float = 0.0005,
    plane_normal: NDArray[np.float64] | None = None,
) -> tuple[Mat4, NDArray[np.float64]]:
    """Refine ``init`` (env_from_object) by the (M, 3) scene points' distances to the model's
    tangent planes: each scene point within ``reach_m`` pairs with its nearest model sample
    and is weighted by Tukey's biweight at 4.685 × the residuals' robust σ (1.4826 × MAD,
    at least ``sigma_floor_m``; at most ``reach_m``). Returns (pose, (M,) final weights).
    ``plane_normal`` (3,) unit: only turns about it and shifts across it (an object resting
    on a plane keeps its tilt and height).

    The model is exact and the scan is the measurement, so the residuals are the scan's
    errors: no scene normals (blurred over 2 voxels on a noisy scan), no hidden model parts
    pairing with something, and a smooth cost that converges to the same pose from any
    start within its reach; what stands around (the floor smeared into an object's foot,
    a neighbour) falls outside the biweight."""
    pose = init.copy()
    weights = np.zeros(len(scene))
    free = np.eye(6) if plane_normal is None else _plane_motions(plane_normal)
    for _ in range(iters):
        x, _, weights = _tukey_step(surface, scene, pose, reach_m, sigma_floor_m, free)
        if x is None:
            break
        step = np.eye(4)
        step[:3, :3] = rotation_from_rotvec(x[:3])
        step[:3, 3] = x[3:]
        pose = step @ pose
        if np.linalg.norm(x[:3]) < 1e-6 and np.linalg.norm(x[3:]) < 1e-6:
            break
    return pose, weights


def rotation_slack_deg(
    surface: ModelSurface,
    scene: Points,
    weights: NDArray[np.float64],
    pose: Mat4,
    free_axis_object: NDArray[np.float64] | None = None,
) -> float:
    """The rotation, degrees, that the scan's residual level can hide: the robust σ of the
    weighted residuals at ``pose`` divided by how fast the weakest rotation (translation
    free to follow) raises the RMS residual, ``sqrt(λ_min / Σw)`` metres per radian (λ_min
    of the Schur complement of the weighted point-to-plane normal matrix). A scan that
    shows faces facing every way has a fast-rising weakest rotation; a flat object seen from
    above has an in-plane turn that nothing raises (180 when nothing holds it at all).
    ``free_axis_object``: (3,) unit axis of a continuous symmetry (object frame), whose
    turn is left out: it changes nothing."""
    used = weights > 0
    if used.sum() < 10:
        return 180.0
    rot, t = pose[:3, :3], pose[:3, 3]
    q = scene[used]
    _, idx = surface.tree.query((q - t) @ rot)
    p = surface.points[idx] @ rot.T + t
    n = surface.normals[idx] @ rot.T
    r = np.einsum("ij,ij->i", p - q, n)
    w = weights[used]
    sigma = 1.4826 * float(np.median(np.abs(r[w > 0.5]))) if (w > 0.5).any() else 0.0
    centre = np.average(p, axis=0, weights=w)
    jac = np.hstack([np.cross(p - centre, n), n]) * np.sqrt(w)[:, None]
    h = jac.T @ jac
    try:
        schur = h[:3, :3] - h[:3, 3:] @ np.linalg.solve(h[3:, 3:], h[3:, :3])
    except np.linalg.LinAlgError:
        return 180.0
    if free_axis_object is not None:
        axis = rot @ np.asarray(free_axis_object, dtype=np.float64)
        basis = np.linalg.svd(np.eye(3) - np.outer(axis, axis))[0][:, :2]
        schur = basis.T @ schur @ basis
    lam = float(np.linalg.eigvalsh(schur)[0])
    rise = np.sqrt(max(lam, 0.0) / float(w.sum()))
    if rise <= 0.0:
        return 180.0
    return float(min(np.degrees(sigma / rise), 180.0))


def truncated_score(tree: cKDTree, points: Points, tau: float) -> float:
    """Mean of ``max(0, 1 − (d/τ)²)`` over (N, 3) points, ``d`` the distance to the scene."""
    d, _ = tree.query(points, distance_upper_bound=tau)
    d = np.where(np.isfinite(d), d, tau)
    return float(np.mean(np.clip(1.0 - (d / tau) ** 2, 0.0, None)))


def fitness_and_rmse(tree: cKDTree, points: Points, max_distance_m: float) -> tuple[float, float]:
    """Open3D's registration figures of (N, 3) posed points against a scene tree: the share
    with a scene point within ``max_distance_m``, and those distances' RMS (metres; 0 when
    none). Summed here in one order, so they do not depend on how many threads run."""
    d, _ = tree.query(points, distance_upper_bound=max_distance_m)
    return inlier_figures(d)


def median_spacing_m(points: Points, sample: int, seed: int) -> float:
    """Median nearest-neighbour distance of (N ≥ 2, 3) points, metres, over a seeded
    sample of at most ``sample`` of them."""
    rng = np.random.default_rng(seed)
    pick = points
    if len(points) > sample:
        pick = points[rng.choice(len(points), sample, replace=False)]
    # unbalanced: built in half the time; a nearest distance does not depend on the tree
    d, _ = cKDTree(points, balanced_tree=False, compact_nodes=False).query(pick, k=2)
    return float(np.median(d[:, 1]))


def inlier_figures(distances: NDArray[np.float64]) -> tuple[float, float]:
    """(share of the (N,) distances that are finite, their RMS in metres; 0 when none): the
    fitness and inlier RMSE of points whose distances beyond the inlier distance are inf."""
    near = distances[np.isfinite(distances)]
    if near.size == 0:
        return 0.0, 0.0
    return near.size / len(distances), float(np.sqrt(np.mean(near**2)))


def exclusion_factor(
    posed: Points,
    support: NDArray[np.float64] | None,
    free_space: Sequence[DepthMap],
    band: float,
) -> float:
    """1 − 3 × the share of (N, 3) posed model points where the object cannot be, at least
    0: more than ``band`` below the support plane (an object does not sink into the floor
    it stands on) or more than ``band`` in front of the surface that more cameras of the
    capture saw behind them than saw a surface there (it does not fill space the cameras
    saw through: a hammer turned over about its handle puts its claw there; a majority,
    since a sparse stretch of the cloud, such as a far table top, leaves holes in single
    z-buffers that show the floor through a real object)."""
    cannot = np.zeros(len(posed), dtype=bool)
    if support is not None:
        cannot |= posed @ support[:3] + support[3] < -band
    if free_space:
        empty, there = depth_votes(posed[~cannot], free_space, band)
        cannot[~cannot] = empty > there
    return max(0.0, 1.0 - 3.0 * float(np.mean(cannot)))


def lowest_height(posed: Points, support: NDArray[np.float64]) -> float:
    """Signed height (metres) of the lowest of (N, 3) posed points above the support plane
    ``[n, d]`` (negative: sunk into it)."""
    return float(np.min(posed @ support[:3])) + float(support[3])


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
    if support is None or max_sink_m <= 0:
        return env_from_object
    posed = transform_points(env_from_object, model_points)
    lowest = lowest_height(posed, support)
    if not -max_sink_m <= lowest < 0.0 or not plane_beyond(posed, on_support, clearance_m):
        return env_from_object
    out = env_from_object.copy()
    out[:3, 3] -= lowest * support[:3]
    return out


def plane_beyond(posed: Points, on_support: Points, clearance_m: float) -> bool:
    """Whether the support plane reaches beyond the (N, 3) posed model: at least 30 of the
    (M, 3) scene points ``on_support`` lie more than ``clearance_m`` from it (an object's
    own flat face is no floor)."""
    if len(on_support) < 30:
        return False
    d, _ = cKDTree(posed).query(on_support, distance_upper_bound=clearance_m)
    return int(np.count_nonzero(~np.isfinite(d))) >= 30


def hull_normals(points_object: Points, centre_object: NDArray[np.float64]) -> NDArray[np.float64]:
    """(F, 3) unit outward normals of the faces an object can rest on: the faces of the
    convex hull of (N ≥ 4, 3) model points (object frame) that hold ``centre_object`` (3,),
    its centre of mass, above them. Coplanar hull triangles are one face; a face whose
    polygon does not contain the centre's foot (a rounded flank's sliver) would tip over."""
    hull = ConvexHull(points_object)
    planes = np.round(hull.equations, 6)
    _, group, counts = np.unique(planes, axis=0, return_inverse=True, return_counts=True)
    out = []
    for facets in np.split(np.argsort(group.ravel(), kind="stable"), np.cumsum(counts)[:-1]):
        normal, offset = hull.equations[facets[0], :3], hull.equations[facets[0], 3]
        corners = points_object[np.unique(hull.simplices[facets])]
        foot = centre_object - (normal @ centre_object + offset) * normal
        if _inside_polygon(corners, foot, normal):
            out.append(normal)
    return np.asarray(out, dtype=np.float64).reshape(-1, 3)


def _inside_polygon(
    corners: Points, point: NDArray[np.float64], normal: NDArray[np.float64]
) -> bool:
    """Whether ``point`` (3,) lies inside the convex polygon of the (K, 3) coplanar
    ``corners`` with unit ``normal`` (False for a degenerate polygon)."""
    if len(corners) < 3:
        return False
    u, v = perpendicular_pair(normal)
    flat = np.column_stack([corners @ u, corners @ v])
    try:
        polygon = ConvexHull(flat)
    except QhullError:
        return False
    q = np.array([point @ u, point @ v])
    return bool(np.all(polygon.equations[:, :2] @ q + polygon.equations[:, 2] <= 0.0))


def resting_turn(
    rotation: NDArray[np.float64],
    bases_object: NDArray[np.float64],
    faces_object: NDArray[np.float64],
    up: NDArray[np.float64],
    max_tilt_deg: float,
) -> NDArray[np.float64] | None:
    """The smallest (3, 3) turn that sets a face of an object turned by ``rotation`` flat on
    a level support: of the (B, 3) outward normals ``bases_object`` (object frame: the
    faces it is meant to stand on), the one nearest down (−``up``) when within
    ``max_tilt_deg``, else of the (F, 3) ``faces_object``, turned exactly down. None when
    no face is that near (the object leans on something, or is not at rest)."""
    down = -normalised(np.asarray(up, dtype=np.float64)[None, :])[0]
    limit = np.cos(np.radians(max_tilt_deg))
    face = None
    for normals in (bases_object @ rotation.T, faces_object @ rotation.T):
        cos_all = normals @ down
        if len(cos_all) and cos_all.max() >= limit:
            face = normals[int(np.argmax(cos_all))]
            break
    if face is None:
        return None
    cos = float(np.clip(face @ down, -1.0, 1.0))
    axis = np.cross(face, down)
    sin = float(np.linalg.norm(axis))
    if sin < 1e-12:
        return np.eye(3)
    return rotation_from_rotvec(axis / sin * np.arctan2(sin, cos))
