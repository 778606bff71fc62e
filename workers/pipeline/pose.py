"""Estimate one object's pose in the environment: ``env_from_object`` (4×4, metres).

Input: a :class:`~workers.pipeline.model.PreparedModel` (object frame) and the scene cloud
(environment frame, metres) with the changed cluster's points or centre. Method:

1. crop a sphere of ``crop_factor × diameter`` around the cluster (a thresholded cluster is
   only part of the object; grown to cover the cluster) and downsample it at the model's
   feature voxel ``v``; scene normals are used as given (when absent: estimated, oriented
   away from the cluster centre, near-horizontal ones facing up);
2. FPFH + RANSAC global registration, scene → model against the model's whole-model and
   per-view descriptors, with ``n_seeds`` seeds (one seed in five found the drill on real
   data); each candidate is polished by a short point-to-plane ICP and scored by a
   truncated-quadratic inlier score. Extra candidates: ICP from a previous pose when one
   is given, and the best candidates turned 180° about each principal axis and about the
   model's near-symmetries (partial views of elongated objects swap their ends);
3. the best ``n_refine`` distinct candidates are refined by multi-scale point-to-plane ICP
   (``1.5v`` → ``0.25v``, pairs with incompatible normals ignored) and re-scored at
   ``0.3v``; the winner gets a last ICP on every model point and, if enabled and both
   clouds have colour, coloured ICP (kept only if the geometric fit holds);
4. verification: ``fitness`` (fraction of model points with a scene point within
   ``inlier_distance_m``), ``inlier_rmse_m``, the share of cluster points explained by
   the posed model, and the score of the best *distinct* alternative; ``verified``
   combines them with :class:`PoseOptions` thresholds. While not verified, steps 2–4 run
   again with new seeds, up to ``max_rounds`` rounds;
5. symmetry: among the equivalent poses ``env_from_object @ S`` one canonical pose is
   published — the one whose model colours match the scene's clearly best when colour
   breaks a discrete symmetry (a label), else closest to a previous pose if given, else
   the one whose object up axis
   agrees best with the environment up (+z), ties broken by the smallest rotation — so a
   symmetric object is never published upside down because the fit is equally good.

Deterministic for a given ``PoseOptions.seed``. Raises RegistrationError when no
candidate is plausible, InputError/ShapeError for unusable inputs.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from workers.pipeline.compare.visibility import DepthMap, seen_empty_counts
from workers.pipeline.errors import InputError, RegistrationError, ShapeError
from workers.pipeline.geometry import (
    Mat4,
    Points,
    as_mat4,
    as_points,
    invert_rigid,
    make_rigid,
    rotation_angle_deg,
    transform_points,
)
from workers.pipeline.model import PreparedModel, fpfh_features, load_prepared, make_cloud
from workers.pipeline.symmetry import SymmetrySpec

REG = o3d.pipelines.registration


#: the rejection a near-tie in 3D gets; the caller may settle it with 2D evidence
RUNNER_UP_REASON = "a distinct pose scores"


@dataclass(frozen=True)
class PoseOptions:
    """Pose estimation settings; distances are in units of the model's voxel ``v``
    (``diameter / voxel_divisor``) unless named ``_m``.

    ``colored_icp`` is off by default: on YCB partial views with exact texture colours it
    was accepted by the fit checks yet moved the rotation from 0.1–0.2° to about 1° off.

    ``support_band_voxels``: the plane the object stands on (floor, table; found under the
    cluster) is removed from the scene up to this height (at most ``max_inlier_distance_m``),
    and a candidate is penalised for the share of model points sunk below it by more than
    that band, or lying that far in front of what a camera saw (when ``free_space`` depth
    maps are given); 0 disables the support plane. ``max_sink_m``: a final pose whose lowest
    model point lies below that plane by at most this much is lifted onto it (an object
    does not sink into what it stands on); 0 disables.

    ``colour_margin``: a symmetric object whose colours break its symmetry (a label) is
    published in the equivalent pose whose model colours correlate best with the scene's,
    when that correlation beats every other equivalent's by this margin.

    Verification: ``verified`` needs ``fitness ≥ min_fitness`` (model points within
    ``inlier_voxels·v`` of the scene, at most ``max_inlier_distance_m`` — the scan's noise,
    not the object's size, bounds a real inlier; a single view sees 30–60 % of an object),
    ``inlier_rmse ≤ max_rmse_voxels·v`` and, when cluster points are given,
    ``cluster_coverage ≥ min_cluster_coverage`` (the share of cluster points within a
    tolerance of the posed model: the change must be explained by the object; the
    tolerance is 3σ of the cluster's own scatter about the posed model, σ = 1.4826 × the
    median distance, clipped to ``coverage_voxels·v`` … ``max_coverage_voxels·v`` and
    ``max_inlier_distance_m`` — a reconstructed cloud scatters 2–4 mm about the true surface,
    and a cluster that includes something else leaves it uncovered by centimetres),
    and no *distinct* candidate (modulo symmetry) scoring above ``max_runner_up_ratio`` ×
    the best: two different poses that explain the data about equally well (a wall sliding
    along a wall) are not a verified pose.
    """

    crop_factor: float = 0.7
    n_seeds: int = 5  # per round; up to max_rounds rounds while the pose is not verified
    min_seeds: int = 2  # per round; more only until two starts agree on the best candidate
    ransac_max_iterations: int = 20000
    ransac_confidence: float = 0.999
    ransac_distance_voxels: float = 1.5
    mutual_filter: bool = False
    ransac_direction: str = "scene_to_model"
    edge_length_check: float = 0.9
    score_voxels: float = 0.5
    n_refine: int = 3
    n_flip_bases: int = 2
    max_rounds: int = 2
    fine_score_voxels: float = 0.3
    icp_scales_voxels: tuple[float, ...] = (1.5, 0.6, 0.25)
    icp_max_iterations: int = 20
    colored_icp: bool = False
    inlier_voxels: float = 0.5
    max_inlier_distance_m: float = 0.01
    min_fitness: float = 0.25
    max_rmse_voxels: float = 0.3
    coverage_voxels: float = 0.5
    max_coverage_voxels: float = 1.5
    min_cluster_coverage: float = 0.85
    colour_margin: float = 0.1
    support_band_voxels: float = 0.5
    max_sink_m: float = 0.01
    max_runner_up_ratio: float = 0.85
    seed: int = 0


POSE_PRESETS: dict[str, PoseOptions] = {
    "default": PoseOptions(),
    "fast": PoseOptions(n_seeds=3, ransac_max_iterations=10000, max_rounds=1),
    "thorough": PoseOptions(n_seeds=8, ransac_max_iterations=100000, max_rounds=4),
}


@dataclass(frozen=True)
class SceneCloud:
    """Scene points in the environment frame: (N, 3) metres, optional unit normals and
    colours in [0, 1], both (N, 3). Non-finite points are dropped on construction via
    :meth:`create`."""

    points: Points
    normals: Points | None = None
    colors: Points | None = None

    @classmethod
    def create(
        cls, points: ArrayLike, normals: ArrayLike | None = None, colors: ArrayLike | None = None
    ) -> SceneCloud:
        """Check shapes (ShapeError) and drop non-finite rows."""
        p = as_points(points, "scene points")
        n = None if normals is None else as_points(normals, "scene normals")
        c = None if colors is None else as_points(colors, "scene colors")
        for name, a in (("normals", n), ("colors", c)):
            if a is not None and a.shape != p.shape:
                raise ShapeError(f"scene {name} must match points {p.shape}, got {a.shape}")
        keep = np.isfinite(p).all(axis=1)
        if n is not None:
            keep &= np.isfinite(n).all(axis=1)
        return cls(p[keep], None if n is None else n[keep], None if c is None else c[keep])

    @classmethod
    def from_file(cls, path: Path, viewpoint_env: ArrayLike | None = None) -> SceneCloud:
        """Read a cloud file; without normals, estimate them and orient them towards
        ``viewpoint_env`` (default the origin, the camera of a single depth frame)."""
        pcd = o3d.io.read_point_cloud(Path(path)).remove_non_finite_points()
        if len(pcd.points) == 0:
            raise InputError(f"{Path(path).name}: no finite points could be read")
        if not pcd.has_normals():
            pts = np.asarray(pcd.points)
            ext = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
            pcd.estimate_normals(
                o3d.geometry.KDTreeSearchParamHybrid(radius=ext / np.sqrt(len(pts)) * 6, max_nn=30)
            )
            vp = np.zeros(3) if viewpoint_env is None else np.asarray(viewpoint_env, np.float64)
            pcd.orient_normals_towards_camera_location(vp)
        return cls.create(
            np.asarray(pcd.points),
            np.asarray(pcd.normals),
            np.asarray(pcd.colors) if pcd.has_colors() else None,
        )


@dataclass(frozen=True)
class Trial:
    """One global-registration candidate after its short ICP polish."""

    source: str
    score: float
    fitness: float
    inlier_rmse_m: float
    seconds: float
    env_from_object: Mat4


@dataclass(frozen=True, eq=False)
class PoseResult:
    """Pose of one object. ``env_from_object``: 4×4 float64 mapping object-model points
    (metres) into the environment frame. ``equivalent_poses``: other poses that fit equally
    well by symmetry (continuous symmetry: 8 samples per discrete element; the axis is
    ``symmetry_axis_env`` through ``symmetry_origin_env``). ``chosen_by``: "unique",
    "colour", "previous" or "up". ``cluster_coverage`` is None when no cluster points were given.
    ``alternatives``: the other refined hypotheses as (fine score, env_from_object), best
    first — for a caller whose re-projection check rejects the chosen pose."""

    env_from_object: Mat4
    fitness: float
    inlier_rmse_m: float
    inlier_distance_m: float
    score: float
    runner_up_score: float
    cluster_coverage: float | None
    verified: bool
    rejections: tuple[str, ...]
    ambiguous: bool
    equivalent_poses: tuple[Mat4, ...]
    symmetry_axis_env: NDArray[np.float64] | None
    symmetry_origin_env: NDArray[np.float64] | None
    chosen_by: str
    source: str
    trials: tuple[Trial, ...]
    n_scene_points: int
    alternatives: tuple[tuple[float, Mat4], ...] = ()
    timings_s: dict[str, float] = field(default_factory=dict)

    def quality_json(self) -> dict[str, Any]:
        """The ``pose_quality`` object of the comparison contract."""
        return {
            "fitness": self.fitness,
            "inlier_rmse": self.inlier_rmse_m,
            "verified": self.verified,
            "ambiguous": self.ambiguous,
            "equivalent_poses": [p.tolist() for p in self.equivalent_poses],
        }


# --------------------------------------------------------------------------- helpers


def random_rigid(rng: np.random.Generator, max_translation_m: float = 1.0) -> Mat4:
    """A uniformly random rotation (unit quaternion) with translation uniform in ±max."""
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    r = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    return make_rigid(r, rng.uniform(-max_translation_m, max_translation_m, 3))


def symmetric_pose_error(
    estimated_env_from_object: ArrayLike,
    true_env_from_object: ArrayLike,
    symmetry: SymmetrySpec,
    point_object: ArrayLike | None = None,
) -> tuple[float, float]:
    """(metres, degrees) pose error minimised over the symmetry group: the equivalent pose
    with the smallest rotation error, and its translation error measured at
    ``point_object`` ((3,), object frame; default the symmetry origin for continuous
    symmetry, else the object origin). Continuous symmetry is solved in closed form."""
    est = as_mat4(estimated_env_from_object, "estimated")
    true = as_mat4(true_env_from_object, "true")
    if point_object is None:
        point = (
            symmetry.origin
            if symmetry.kind == "continuous" and symmetry.origin is not None
            else np.zeros(3)
        )
    else:
        point = np.asarray(point_object, dtype=np.float64).reshape(3)
    if symmetry.kind == "continuous" and symmetry.axis is not None:
        # trace(R_true^T R_est R_axis(θ) R_d) = A + B cos θ + C sin θ: maximise in closed form
        ax = symmetry.axis
        k = np.array([[0.0, -ax[2], ax[1]], [ax[2], 0.0, -ax[0]], [-ax[1], ax[0], 0.0]])
        elements = []
        for d in symmetry.rotations:
            m = d[:3, :3] @ true[:3, :3].T @ est[:3, :3]
            a_ = float(ax @ m @ ax)
            b_ = float(np.trace(m)) - a_
            c_ = float(np.trace(m @ k))
            elements.append(symmetry.continuous_rotation(float(np.arctan2(c_, b_))) @ d)
        stack = np.stack(elements)
    else:
        stack = np.stack(list(symmetry.rotations))
    cand = est @ stack  # (K, 4, 4)
    rel = np.einsum("ji,kjl->kil", true[:3, :3], cand[:, :3, :3])  # R_true^T R_k
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    best = int(np.argmax(cos))
    p_est = cand[best, :3, :3] @ point + cand[best, :3, 3]
    p_true = true[:3, :3] @ point + true[:3, 3]
    return float(np.linalg.norm(p_est - p_true)), float(np.degrees(np.arccos(cos[best])))


def _normalised(a: Points) -> Points:
    out: Points = a / np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-12)
    return out


def _crop(
    scene: SceneCloud, centre: NDArray[np.float64], radius: float
) -> tuple[Points, Points | None, Points | None]:
    keep = np.einsum("ij,ij->i", scene.points - centre, scene.points - centre) <= radius * radius
    return (
        scene.points[keep],
        None if scene.normals is None else scene.normals[keep],
        None if scene.colors is None else scene.colors[keep],
    )


def _orient_scene_normals(
    normals: Points, points: Points, centre: NDArray[np.float64], up: NDArray[np.float64]
) -> Points:
    """Orient estimated (N, 3) normals without a viewpoint: away from the cluster centre,
    except near-horizontal surfaces (normal within 37° of ``up``), which face up — the table
    under an object is seen from above, and an object's hidden underside is not scanned."""
    out = normals.copy()
    out[np.einsum("ij,ij->i", out, points - centre) < 0] *= -1.0
    along = out @ up
    out[(np.abs(along) > 0.8) & (along < 0)] *= -1.0
    return out


def _cluster_coverage(cluster: Points, posed_model: Points, v: float, o: PoseOptions) -> float:
    """Share of (K, 3) cluster points within the noise-scaled tolerance of the (N, 3) posed
    model points (see :class:`PoseOptions`)."""
    hi = min(o.max_coverage_voxels * v, o.max_inlier_distance_m)
    d, _ = cKDTree(posed_model).query(cluster, distance_upper_bound=hi)
    d_med = float(np.median(np.where(np.isfinite(d), d, hi)))
    tol = float(np.clip(3.0 * 1.4826 * d_med, min(o.coverage_voxels * v, hi), hi))
    return float(np.mean(d <= tol))


def _colour_agreement(
    model: PreparedModel, env_from_object: Mat4, target: _Target, dist: float
) -> float:
    """Correlation (channel means removed) of the model's colours with the colours of the
    nearest scene points within ``dist`` metres; NaN without colours or with < 100 pairs."""
    if model.colors is None or target.colors is None:
        return float("nan")
    d, idx = target.tree.query(
        transform_points(env_from_object, model.points), distance_upper_bound=dist
    )
    ok = np.isfinite(d)
    if ok.sum() < 100:
        return float("nan")
    a = model.colors[ok] - model.colors[ok].mean(axis=0)
    b = target.colors[idx[ok]] - target.colors[idx[ok]].mean(axis=0)
    den = float(np.sqrt((a * a).sum() * (b * b).sum()))
    return float((a * b).sum() / den) if den > 0 else float("nan")


def _rounded_rigid(a_from_b: Mat4, decimals: int) -> Mat4:
    """``a_from_b`` rounded to ``decimals`` and made a rotation again (Gram-Schmidt in
    element-wise arithmetic, so that equal inputs give bit-identical outputs)."""
    r = np.round(a_from_b[:3, :3], decimals)
    x = r[:, 0] / np.sqrt((r[:, 0] ** 2).sum())
    y = r[:, 1] - (x * r[:, 1]).sum() * x
    y = y / np.sqrt((y**2).sum())
    return make_rigid(np.column_stack([x, y, np.cross(x, y)]), np.round(a_from_b[:3, 3], decimals))


def _moment_candidates(model: PreparedModel, cluster: Points) -> list[Mat4]:
    """The four proper rotations that map the model's principal axes onto the (K, 3)
    cluster's, centroid on centroid: a start independent of descriptors, which a flat or
    elongated object with few distinctive features (a hammer) needs."""
    if len(cluster) < 10:
        return []
    m_c = model.points - model.centre_object
    s_mean = cluster.mean(axis=0)
    _, e_m = np.linalg.eigh(m_c.T @ m_c)
    _, e_s = np.linalg.eigh((cluster - s_mean).T @ (cluster - s_mean))
    e_m[:, 2] *= np.sign(np.linalg.det(e_m))  # right-handed axes: even sign flips are proper
    e_s[:, 2] *= np.sign(np.linalg.det(e_s))
    out = []
    for signs in ((1, 1, 1), (-1, -1, 1), (-1, 1, -1), (1, -1, -1)):
        r = e_s @ np.diag(signs) @ e_m.T
        out.append(make_rigid(r, s_mean - r @ model.centre_object))
    return out


def _support_plane(
    points: Points,
    normals: Points,
    up: NDArray[np.float64],
    cluster: Points,
    band: float,
    seed: int,
) -> NDArray[np.float64] | None:
    """The plane (4,) ``[n, d]`` (unit ``n`` within 10° of ``up``, height ``n·p + d``) that the
    object stands on: the largest plane (RANSAC, 200 draws, seeded) of the near-horizontal
    (N, 3) scene points that at least 10 % of them fit within ``band / 2`` and that the
    (K, 3) cluster's median lies more than ``band`` above (a box's own top face is not its
    support); None if none."""
    rng = np.random.default_rng(seed)
    horizontal = points[np.abs(normals @ up) > np.cos(np.radians(25.0))]
    for _ in range(2):
        if len(horizontal) < 100:
            return None
        tri = horizontal[rng.integers(0, len(horizontal), size=(200, 3))]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        n *= np.where(n @ up < 0, -1.0, 1.0)[:, None]
        ok = n @ up > np.cos(np.radians(10.0))
        if not ok.any():
            return None
        n, d = n[ok], -np.einsum("ij,ij->i", n[ok], tri[ok, 0])
        sample = horizontal[rng.choice(len(horizontal), min(len(horizontal), 2000), replace=False)]
        counts = (np.abs(sample @ n.T + d) < band / 2).sum(axis=0)
        best = int(np.argmax(counts))
        inliers = horizontal[np.abs(horizontal @ n[best] + d[best]) < band / 2]
        if len(inliers) < 0.1 * len(horizontal):
            return None
        centre = inliers.mean(axis=0)
        normal = np.linalg.svd(inliers - centre, full_matrices=False)[2][2]
        normal = normal if normal @ up > 0 else -normal
        out = np.append(normal, -normal @ centre)
        if out[:3] @ up < np.cos(np.radians(10.0)):
            return None
        if float(np.median(cluster @ out[:3] + out[3])) > band:
            return out
        # a horizontal face of the object itself: look below it
        horizontal = horizontal[horizontal @ out[:3] + out[3] < -band]
    return None


def _exclusion_factor(
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


def _out_of_support(
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
    the posed model (an object's own flat face is no floor). ICP onto a reconstruction,
    whose stereo rounds an object's top edges down, left every bench pose 1-8 mm sunk."""
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


def _truncated_score(tree: cKDTree, points: Points, tau: float) -> float:
    d, _ = tree.query(points, distance_upper_bound=tau)
    d = np.where(np.isfinite(d), d, tau)
    return float(np.mean(np.clip(1.0 - (d / tau) ** 2, 0.0, None)))


class _Target:
    """A scene cloud with unit normals and a KD-tree built once for every ICP run."""

    def __init__(self, pcd: o3d.geometry.PointCloud) -> None:
        self.points = np.asarray(pcd.points, dtype=np.float64).copy()
        self.normals = _normalised(np.asarray(pcd.normals, dtype=np.float64))
        self.colors = np.asarray(pcd.colors, dtype=np.float64).copy() if pcd.has_colors() else None
        self.tree = cKDTree(self.points)


def _skew_exp(w: NDArray[np.float64]) -> NDArray[np.float64]:
    angle = float(np.linalg.norm(w))
    if angle < 1e-12:
        return np.eye(3)
    k = w / angle
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    out: NDArray[np.float64] = np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * (kx @ kx)
    return out


def _icp(
    src: Points, src_normals: Points, target: _Target, init: Mat4, dist: float, iters: int
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
        step[:3, :3] = _skew_exp(x[:3])
        step[:3, 3] = x[3:]
        pose = step @ pose
        if np.linalg.norm(x[:3]) < 1e-5 and np.linalg.norm(x[3:]) < 1e-4 * dist:
            break
    return pose


def _canonical(
    env_from_object: Mat4,
    symmetry: SymmetrySpec,
    up_object: NDArray[np.float64],
    up_env: NDArray[np.float64],
    previous: Mat4 | None,
    colour: Callable[[Mat4], float] | None = None,
    colour_margin: float = 0.1,
) -> tuple[Mat4, str, list[Mat4]]:
    """Pick one pose among ``env_from_object @ S``; return (pose, chosen_by, equivalents).

    Order: ``colour`` (a discrete group whose colours break it: among the elements whose
    object up agrees best with ``up_env`` — never upside down — the one whose colour
    agreement beats the others by ``colour_margin``), then ``previous``, then ``up``."""
    if not symmetry.is_symmetric:
        return env_from_object, "unique", []
    if colour is not None and symmetry.kind == "discrete" and symmetry.appearance_breaks:
        poses = [env_from_object @ s for s in symmetry.rotations]
        ups = np.array([p[:3, :3] @ up_object @ up_env for p in poses])
        upright = [p for p, u in zip(poses, ups, strict=True) if u >= ups.max() - 0.02]
        scores = np.array([colour(p) for p in upright])
        if len(upright) > 1 and np.isfinite(scores).all():
            order = np.argsort(-scores)
            if scores[order[0]] - scores[order[1]] >= colour_margin:
                chosen = upright[int(order[0])]
                return chosen, "colour", [chosen @ s for s in symmetry.rotations[1:]]
    if symmetry.kind == "continuous":
        grid = [
            env_from_object @ symmetry.continuous_rotation(a) @ s
            for s in symmetry.rotations
            for a in np.radians(np.arange(0.0, 360.0, 0.5))
        ]
    else:
        grid = [env_from_object @ s for s in symmetry.rotations]
    rots = np.stack([g[:3, :3] for g in grid])
    if previous is not None:
        cos = (np.einsum("nij,ij->n", rots, previous[:3, :3]) - 1.0) / 2.0  # trace(R_prev^T R)
        best = int(np.argmax(cos))
        chosen_by = "previous"
    else:
        up = rots @ up_object @ up_env
        near = up >= up.max() - 0.02  # within ~11° of the best up agreement
        closeness = np.trace(rots, axis1=1, axis2=2)  # larger = smaller rotation angle
        best = int(np.argmax(np.where(near, closeness, -np.inf)))
        chosen_by = "up"
    chosen = grid[best]
    samples = symmetry.sample(8) if symmetry.kind == "continuous" else list(symmetry.rotations)
    equivalents = [chosen @ s for s in samples if rotation_angle_deg(s[:3, :3]) > 1e-3]
    return chosen, chosen_by, equivalents


# --------------------------------------------------------------------------- main entry


def estimate_pose(
    model: PreparedModel,
    scene: SceneCloud,
    *,
    cluster_points_env: ArrayLike | None = None,
    centre_env: ArrayLike | None = None,
    previous_env_from_object: ArrayLike | None = None,
    up_env: ArrayLike = (0.0, 0.0, 1.0),
    free_space: Sequence[DepthMap] = (),
    options: PoseOptions = POSE_PRESETS["default"],
) -> PoseResult:
    """Register ``model`` into ``scene`` near a changed cluster; return ``env_from_object``.

    ``cluster_points_env``: (K, 3) points of the changed cluster (env frame, metres), or
    ``centre_env`` (3,) when only a centre is known; one is required. The crop radius is
    ``crop_factor × diameter`` (grown to cover the cluster plus a quarter diameter, at most
    one diameter). ``previous_env_from_object``: a known earlier pose (object moved), tried
    as an extra ICP start and used to choose among symmetric poses. ``up_env``: the
    environment's up direction. ``free_space``: z-buffers of the capture the scene came
    from, one per camera (:func:`~workers.pipeline.compare.stage.render_depth_maps`); a
    candidate is penalised for model points where a camera saw through. Raises
    RegistrationError when the crop is too sparse or no candidate explains any of it.
    """
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    if not isinstance(scene, SceneCloud):
        raise ShapeError("scene must be a SceneCloud (use SceneCloud.create)")
    cluster = (
        None if cluster_points_env is None else as_points(cluster_points_env, "cluster points")
    )
    if cluster is not None and len(cluster) == 0:
        cluster = None
    if cluster is not None:
        centre = cluster.mean(axis=0)
    elif centre_env is not None:
        centre = np.asarray(centre_env, dtype=np.float64).reshape(-1)
        if centre.shape != (3,) or not np.isfinite(centre).all():
            raise ShapeError(f"centre_env must be a finite (3,), got {centre.shape}")
    else:
        raise InputError("estimate_pose needs cluster_points_env or centre_env")
    previous = (
        None if previous_env_from_object is None else as_mat4(previous_env_from_object, "previous")
    )
    up = np.asarray(up_env, dtype=np.float64).reshape(-1)
    if up.shape != (3,) or np.linalg.norm(up) == 0:
        raise ShapeError("up_env must be a non-zero (3,) vector")
    up = up / np.linalg.norm(up)
    o = options
    if o.max_rounds < 1 or o.n_seeds < 0:
        raise InputError("PoseOptions needs max_rounds ≥ 1 and n_seeds ≥ 0")
    v = model.voxel_m
    diam = model.diameter_m

    # 1. crop and prepare the scene region
    radius = o.crop_factor * diam
    if cluster is not None:
        extent = float(np.sqrt(np.max(np.sum((cluster - centre) ** 2, axis=1))))
        radius = min(max(radius, extent + 0.25 * diam), max(diam, o.crop_factor * diam))
    c_pts, c_nrm, c_col = _crop(scene, centre, radius)
    cluster_low = cluster if cluster is not None else centre[None, :]
    if len(c_pts) < 30:
        raise RegistrationError(
            f"only {len(c_pts)} scene points within {radius:.3f} m of the cluster centre"
        )
    scene_full = make_cloud(c_pts, c_nrm, c_col)
    if len(c_pts) > 4 * len(model.points):
        # a dense reconstruction: v/4 keeps every detail the fit uses, at a fraction of the
        # cost of normals and neighbour queries on every point
        scene_full = scene_full.voxel_down_sample(v / 4)
    f_pts = np.asarray(scene_full.points)
    if c_nrm is None:
        scene_full.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * v, max_nn=30))
        scene_full.normals = o3d.utility.Vector3dVector(
            _orient_scene_normals(np.asarray(scene_full.normals), f_pts, centre, up)
        )
    band = min(o.support_band_voxels * v, o.max_inlier_distance_m)
    support = (
        _support_plane(f_pts, np.asarray(scene_full.normals), up, cluster_low, band, o.seed)
        if o.support_band_voxels > 0
        else None
    )
    on_support = np.zeros((0, 3))
    if support is not None:
        height = f_pts @ support[:3] + support[3]
        on_support = f_pts[np.abs(height) < band / 2]
        # the floor or table the object stands on is not the object: a flat object laid
        # into it upside down fits it better than the object itself
        above = np.flatnonzero(height > band)
        if len(above) >= 30:
            scene_full = scene_full.select_by_index(above.tolist())
    timings["support_removed"] = float(len(f_pts) - len(scene_full.points))
    scene_down = scene_full.voxel_down_sample(v)
    scene_down.normals = o3d.utility.Vector3dVector(_normalised(np.asarray(scene_down.normals)))
    scene_fine = scene_full
    if scene_fine.has_normals():
        scene_fine.normals = o3d.utility.Vector3dVector(_normalised(np.asarray(scene_fine.normals)))
    n_opts = model.summary.get("options", {})
    scene_fpfh = fpfh_features(
        scene_down,
        v,
        float(n_opts.get("normal_radius_voxels", 2.0)),
        float(n_opts.get("feature_radius_voxels", 5.0)),
    )
    target_down = _Target(scene_down)
    target_fine = _Target(scene_fine)
    tree = target_fine.tree
    model_down = make_cloud(model.down_points, model.down_normals, None)
    model_feat = make_cloud(model.feature_points, model.feature_normals, None)
    timings["prepare"] = time.perf_counter() - t_start

    # 2. global candidates: RANSAC with several seeds (+ previous pose)
    t0 = time.perf_counter()
    f_model = REG.Feature()
    f_model.data = np.ascontiguousarray(model.fpfh.T)
    f_scene = REG.Feature()
    f_scene.data = np.ascontiguousarray(scene_fpfh.T)
    checkers = [
        REG.CorrespondenceCheckerBasedOnEdgeLength(o.edge_length_check),
        REG.CorrespondenceCheckerBasedOnDistance(o.ransac_distance_voxels * v),
    ]
    tau = o.score_voxels * v
    trials: list[Trial] = []

    def polish(init: Mat4, source: str, t_begin: float) -> None:
        t = _icp(
            model.down_points, model.down_normals, target_down, init, o.icp_scales_voxels[0] * v, 10
        )
        t = _icp(
            model.down_points, model.down_normals, target_fine, t, o.icp_scales_voxels[1] * v, 10
        )
        # Open3D's multi-threaded RANSAC may return another of several tied hypotheses
        # between runs of one seed; ICP takes them to the same pose up to ~1e-15, and
        # rounding to 1e-9 (far below the accuracy) makes everything after bit-identical
        t = _rounded_rigid(t, 9)
        pts = transform_points(t, model.down_points)
        ev = REG.evaluate_registration(model_down, scene_fine, tau, t)
        excluded = _exclusion_factor(pts, support, free_space, band)
        trials.append(
            Trial(
                source,
                _truncated_score(tree, pts, tau) * excluded,
                float(ev.fitness),
                float(ev.inlier_rmse),
                time.perf_counter() - t_begin,
                t,
            )
        )

    flipped: set[int] = set()
    refined_ids: set[int] = set()
    refined: list[tuple[float, Mat4, Trial]] = []
    model_full = make_cloud(model.points, model.normals, model.colors)
    model_mid = model_full.voxel_down_sample(v / 2)
    tau_fine = o.fine_score_voxels * v
    mid_points = np.asarray(model_mid.points)
    mid_normals = _normalised(np.asarray(model_mid.normals))
    timings["refine"] = 0.0
    # rounds: more RANSAC seeds only while the best pose is not verified (hard views)
    for round_ in range(o.max_rounds):
        t0 = time.perf_counter()
        if round_ == 0 and previous is not None:
            polish(previous, "previous pose", time.perf_counter())
        if round_ == 0 and cluster is not None:
            # the axes of what stands above the support: floor smeared around an object's
            # foot tilts and shifts a flat object's axes (the hammer in 'multiple' got a
            # start 23 mm / 7° off whose ICP stayed there)
            standing = cluster
            if support is not None:
                above = cluster[cluster @ support[:3] + support[3] > band]
                standing = above if len(above) >= 10 else cluster
            for k, init in enumerate(_moment_candidates(model, standing)):
                polish(init, f"cluster axes {k}", time.perf_counter())
        if len(scene_down.points) >= 3:
            for k in range(round_ * o.n_seeds, (round_ + 1) * o.n_seeds):
                if k - round_ * o.n_seeds >= o.min_seeds and _confirmed(
                    trials, model.symmetry, diam, model.centre_object
                ):
                    break  # two independent starts already agree on the best candidate
                tk = time.perf_counter()
                o3d.utility.random.seed(o.seed * 1000 + k)
                # scene → model by default: every visible scene point has its match on the
                # model, while model points on the hidden side only add false matches
                from_scene = o.ransac_direction == "scene_to_model" or (
                    o.ransac_direction == "alternate" and k % 2 == 0
                )
                res = REG.registration_ransac_based_on_feature_matching(
                    scene_down if from_scene else model_feat,
                    model_feat if from_scene else scene_down,
                    f_scene if from_scene else f_model,
                    f_model if from_scene else f_scene,
                    o.mutual_filter,
                    o.ransac_distance_voxels * v,
                    REG.TransformationEstimationPointToPoint(False),
                    3,
                    checkers,
                    REG.RANSACConvergenceCriteria(o.ransac_max_iterations, o.ransac_confidence),
                )
                if len(res.correspondence_set) >= 3:
                    t_res = np.asarray(res.transformation, dtype=np.float64)
                    polish(invert_rigid(t_res) if from_scene else t_res, f"ransac seed {k}", tk)
        if not trials or max(t.score for t in trials) <= 0.0:
            raise RegistrationError(
                f"no registration candidate explains the scene region ({len(trials)} candidates, "
                f"{len(c_pts)} points within {radius:.3f} m)"
            )
        # flip hypotheses: RANSAC on a partial view often gets an elongated object's axes right
        # but its ends swapped; try the best candidates turned 180° about each principal axis
        # and about the model's near-symmetries
        for base in _distinct_ranked(trials, model.symmetry, diam, model.centre_object)[
            : o.n_flip_bases
        ]:
            if id(base) in flipped:
                continue
            flipped.add(id(base))
            for name, flip in _flips(model):
                polish(base.env_from_object @ flip, f"{base.source} + {name}", time.perf_counter())
        timings["global"] = timings.get("global", 0.0) + time.perf_counter() - t0
        t0 = time.perf_counter()
        distinct = _distinct_ranked(trials, model.symmetry, diam, model.centre_object)

        # 3. refinement of the best few distinct candidates and of the model's near-symmetric
        #    alternatives of the best one: multi-scale point-to-plane ICP (coarse scales on a
        #    v/2 subsample, the last on every model point), re-scored at a fine scale where
        #    near-symmetric alternatives separate
        for t in [t for t in distinct if id(t) not in refined_ids][: o.n_refine]:
            refined_ids.add(id(t))
            pose = t.env_from_object
            for scale in o.icp_scales_voxels:
                pose = _icp(
                    mid_points, mid_normals, target_fine, pose, scale * v, o.icp_max_iterations
                )
            posed_mid = transform_points(pose, mid_points)
            score = _truncated_score(tree, posed_mid, tau_fine) * _exclusion_factor(
                posed_mid, support, free_space, band
            )
            refined.append((score, pose, t))
        refined.sort(key=lambda r: -r[0])
        best_fine, env_from_object, best = refined[0]
        env_from_object = _icp(
            model.points,
            model.normals,
            target_fine,
            env_from_object,
            o.icp_scales_voxels[-1] * v,
            o.icp_max_iterations,
        )
        env_from_object = _out_of_support(
            env_from_object, model.points, support, on_support, o.max_sink_m, 2 * v
        )
        runner_up = next(
            (
                r[0]
                for r in refined[1:]
                if distinct_pose(
                    r[1], env_from_object, model.symmetry, diam, centre=model.centre_object
                )
            ),
            0.0,
        )
        dist_in = min(o.inlier_voxels * v, o.max_inlier_distance_m)
        ev = REG.evaluate_registration(model_full, scene_fine, dist_in, env_from_object)
        if o.colored_icp and model.colors is not None and scene_fine.has_colors():
            try:
                col = REG.registration_colored_icp(
                    model_mid,
                    scene_fine,
                    o.icp_scales_voxels[-1] * v,
                    env_from_object,
                    REG.TransformationEstimationForColoredICP(),
                    REG.ICPConvergenceCriteria(1e-7, 1e-7, 30),
                )
                t_col = np.asarray(col.transformation, dtype=np.float64).copy()
                ev_col = REG.evaluate_registration(model_full, scene_fine, dist_in, t_col)
                if (
                    ev_col.fitness >= ev.fitness - 0.01
                    and ev_col.inlier_rmse <= ev.inlier_rmse * 1.05
                ):
                    env_from_object, ev = t_col, ev_col
            except RuntimeError:
                pass  # coloured ICP needs enough coloured correspondences; keep the geometric fit
        timings["refine"] += time.perf_counter() - t0

        # 4. verification figures
        fitness = float(ev.fitness)
        rmse = float(ev.inlier_rmse)
        coverage: float | None = None
        if cluster is not None:
            coverage = _cluster_coverage(
                cluster, transform_points(env_from_object, model.points), v, o
            )
        rejections: list[str] = []
        if fitness < o.min_fitness:
            rejections.append(f"fitness {fitness:.2f} < {o.min_fitness:.2f}")
        max_rmse = min(o.max_rmse_voxels * v, 0.6 * o.max_inlier_distance_m)
        if rmse > max_rmse or fitness == 0.0:
            rejections.append(f"inlier RMSE {rmse * 1000:.1f} mm > {max_rmse * 1000:.1f} mm")
        if runner_up > o.max_runner_up_ratio * best_fine:
            ratio = runner_up / best_fine
            rejections.append(
                f"{RUNNER_UP_REASON} {ratio:.2f} of the best (> {o.max_runner_up_ratio})"
            )
        if coverage is not None and coverage < o.min_cluster_coverage:
            rejections.append(f"cluster coverage {coverage:.2f} < {o.min_cluster_coverage:.2f}")

        if not rejections:
            break
    timings["rounds"] = float(round_ + 1)

    # 5. symmetry: one canonical pose
    chosen, chosen_by, equivalents = _canonical(
        env_from_object,
        model.symmetry,
        model.up_object,
        up,
        previous,
        lambda pose: _colour_agreement(model, pose, target_fine, dist_in),
        o.colour_margin,
    )
    axis_env = origin_env = None
    if model.symmetry.kind == "continuous" and model.symmetry.axis is not None:
        assert model.symmetry.origin is not None
        axis_env = chosen[:3, :3] @ model.symmetry.axis
        origin_env = transform_points(chosen, model.symmetry.origin[None])[0]
    timings["total"] = time.perf_counter() - t_start
    return PoseResult(
        env_from_object=chosen,
        fitness=fitness,
        inlier_rmse_m=rmse,
        inlier_distance_m=dist_in,
        score=best_fine,
        runner_up_score=runner_up,
        cluster_coverage=coverage,
        verified=not rejections,
        rejections=tuple(rejections),
        ambiguous=model.symmetry.is_symmetric,
        equivalent_poses=tuple(equivalents),
        symmetry_axis_env=axis_env,
        symmetry_origin_env=origin_env,
        chosen_by=chosen_by,
        source=best.source,
        trials=tuple(trials),
        n_scene_points=len(c_pts),
        alternatives=tuple((r[0], r[1]) for r in refined[1:]),
        timings_s=timings,
    )


def _confirmed(
    trials: list[Trial], symmetry: SymmetrySpec, diameter: float, centre: NDArray[np.float64]
) -> bool:
    """True when another trial (another start) reached the best-scoring trial's pose."""
    if len(trials) < 2:
        return False
    best = max(trials, key=lambda t: t.score)
    return any(
        t is not best
        and not distinct_pose(
            t.env_from_object, best.env_from_object, symmetry, diameter, centre=centre
        )
        for t in trials
    )


def _distinct_ranked(
    trials: list[Trial], symmetry: SymmetrySpec, diameter: float, centre: NDArray[np.float64]
) -> list[Trial]:
    """Trials by decreasing score, keeping only the best of each set of equivalent poses."""
    out: list[Trial] = []
    for t in sorted(trials, key=lambda t: -t.score):
        if all(
            distinct_pose(
                t.env_from_object, d.env_from_object, symmetry, diameter, 20.0, 0.1, centre
            )
            for d in out
        ):
            out.append(t)
    return out


def _flips(model: PreparedModel) -> list[tuple[str, Mat4]]:
    """180° turns about the principal axes through the centroid, plus near-symmetries."""
    c = model.points - model.centre_object
    _, vecs = np.linalg.eigh(c.T @ c)
    out = []
    for i in range(3):
        r = 2.0 * np.outer(vecs[:, i], vecs[:, i]) - np.eye(3)  # 180° about axis i
        out.append(
            (
                f"flip about principal axis {i}",
                make_rigid(r, model.centre_object - r @ model.centre_object),
            )
        )
    out += [(f"near-symmetry {k}", n) for k, n in enumerate(model.near_symmetries)]
    return out


def _spacing(model: PreparedModel) -> float:
    d, _ = cKDTree(model.points[:2000]).query(model.points[:2000], k=2)
    return float(np.median(d[:, 1]))


def distinct_pose(
    a: Mat4,
    b: Mat4,
    symmetry: SymmetrySpec,
    diameter: float,
    max_deg: float = 5.0,
    max_fraction: float = 0.05,
    centre: NDArray[np.float64] | None = None,
) -> bool:
    """True when two poses differ by more than ``max_deg`` or ``max_fraction`` of the
    diameter (at the symmetry origin), modulo symmetry."""
    dt, dr = symmetric_pose_error(a, b, symmetry, centre)
    return dt > max_fraction * diameter or dr > max_deg


# --------------------------------------------------------------------------- CLI


def _vec3(text: str) -> NDArray[np.float64]:
    parts = [float(x) for x in text.split(",")]
    if len(parts) != 3:
        raise argparse.ArgumentTypeError("expected x,y,z")
    return np.asarray(parts, dtype=np.float64)


def cli(argv: list[str]) -> int:
    """``python -m workers.pipeline pose --model DIR --scene cloud.ply --center x,y,z``."""
    ap = argparse.ArgumentParser(prog="python -m workers.pipeline pose")
    ap.add_argument("--model", type=Path, required=True, help="work dir of `model`")
    ap.add_argument("--scene", type=Path, required=True, help="scene cloud, env frame, metres")
    ap.add_argument(
        "--center",
        "--centre",
        type=_vec3,
        required=True,
        help="cluster centre x,y,z in metres (write --center=-0.1,0.2,0.8 for negatives)",
    )
    ap.add_argument("--viewpoint", type=_vec3, default=None, help="orient estimated normals to it")
    ap.add_argument("--previous", type=Path, default=None, help="JSON 4×4 previous pose")
    ap.add_argument("--preset", default="default", choices=sorted(POSE_PRESETS))
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    try:
        model = load_prepared(args.model)
        scene = SceneCloud.from_file(args.scene, args.viewpoint)
        previous = None if args.previous is None else json.loads(args.previous.read_text())
        result = estimate_pose(
            model,
            scene,
            centre_env=args.center,
            previous_env_from_object=previous,
            options=replace(POSE_PRESETS[args.preset], seed=args.seed),
        )
    except (InputError, RegistrationError, ShapeError) as exc:
        print(exc)
        return 2
    out = {
        "env_from_object": result.env_from_object.tolist(),
        "pose_quality": result.quality_json(),
        "rejections": list(result.rejections),
        "chosen_by": result.chosen_by,
        "source": result.source,
        "trials": [
            {"source": t.source, "score": t.score, "fitness": t.fitness, "seconds": t.seconds}
            for t in result.trials
        ],
        "timings_s": result.timings_s,
    }
    print(json.dumps(out, indent=2))
    return 0
