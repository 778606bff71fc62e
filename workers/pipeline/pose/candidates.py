"""Step 2 of pose estimation: global candidates for ``env_from_object``.

Starts: ICP from a previous pose when one is given (as it stood, and its orientation set on
the cluster, turned about the up axis: a moved object), the cluster's principal axes, and
FPFH + RANSAC (scene → model against the model's whole-model and per-view descriptors,
``n_seeds`` seeds per round, stopping early once two starts agree). Each start is polished
by a short point-to-plane ICP and scored by a truncated-quadratic inlier score (× the
exclusion penalty). The best distinct candidates are also tried turned 180° about each
principal axis and about the model's near-symmetries (partial views of elongated objects
swap their ends).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from workers.pipeline.compare.visibility import DepthMap
from workers.pipeline.errors import RegistrationError
from workers.pipeline.geometry import (
    Mat4,
    Points,
    invert_rigid,
    make_rigid,
    rotation_about_unit_axis,
    rotation_onto,
    rounded_rigid,
    transform_points,
)
from workers.pipeline.model import PreparedModel, make_cloud
from workers.pipeline.model.symmetry_group import SymmetrySpec, symmetric_pose_error
from workers.pipeline.pose.crop import PoseInputs, SceneRegion
from workers.pipeline.pose.fit import (
    exclusion_factor,
    fitness_and_rmse,
    icp_point_to_plane,
    truncated_score,
)
from workers.pipeline.pose.options import PoseOptions
from workers.pipeline.pose.result import Trial
from workers.pipeline.seeded import seeded_open3d

REG = o3d.pipelines.registration
#: a previous orientation set on the cluster is tried turned about the up axis in this many
#: steps (30°: within the polishing ICP's reach of any turn)
PREVIOUS_TURNS = 12


@dataclass(frozen=True)
class FitContext:
    """What every fit of one pose estimate shares: the model, the scene region, the
    capture's ``free_space`` depth maps (one per camera), the options and the
    environment's unit ``up_env`` (3,)."""

    model: PreparedModel
    region: SceneRegion
    free_space: Sequence[DepthMap]
    options: PoseOptions
    up_env: NDArray[np.float64]

    def exclusion(self, posed: Points) -> float:
        """:func:`~workers.pipeline.pose.fit.exclusion_factor` of (N, 3) posed model points."""
        return exclusion_factor(posed, self.region.support, self.free_space, self.region.band_m)

    def upright(self, env_from_object: Mat4) -> bool:
        """:func:`upright` for this model and environment."""
        return upright(env_from_object, self.model.up_object, self.up_env)


def upright(
    env_from_object: Mat4, up_object: NDArray[np.float64], up_env: NDArray[np.float64]
) -> bool:
    """Whether a 4×4 pose keeps the model's own up (3,) (how the library gives it) within
    90° of the environment's up (3,)."""
    return bool(env_from_object[:3, :3] @ up_object @ up_env > 0.0)


@dataclass
class CandidatePool:
    """The candidates of one pose estimate, gathered across rounds (mutable state):
    ``trials`` in the order they were found, ``flipped`` the ids of trials already turned."""

    ctx: FitContext
    model_features: o3d.geometry.PointCloud
    trials: list[Trial] = field(default_factory=list)
    flipped: set[int] = field(default_factory=set)

    @classmethod
    def create(cls, ctx: FitContext) -> CandidatePool:
        """An empty pool with the model's descriptor cloud."""
        m = ctx.model
        return cls(ctx, make_cloud(m.feature_points, m.feature_normals, None))

    def polish(self, init: Mat4, source: str, t_begin: float) -> None:
        """ICP ``init`` (env_from_object) at the first two scales, score it and add the
        :class:`Trial`; ``t_begin`` (perf_counter) is when the start was begun."""
        m, region, o = self.ctx.model, self.ctx.region, self.ctx.options
        v = m.voxel_m
        scales = o.icp_scales_voxels
        t = icp_point_to_plane(
            m.down_points, m.down_normals, region.target_down, init, scales[0] * v, 10
        )
        t = icp_point_to_plane(
            m.down_points, m.down_normals, region.target_fine, t, scales[1] * v, 10
        )
        # rounded to 1e-9 (far below the accuracy): starts that ICP takes to the same pose
        # up to ~1e-15 (its threads sum in any order) go on as one
        t = rounded_rigid(t, 9)
        pts = transform_points(t, m.down_points)
        tau = o.score_voxels * v
        fitness, rmse = fitness_and_rmse(region.target_fine.tree, pts, tau)
        excluded = self.ctx.exclusion(pts)
        self.trials.append(
            Trial(
                source,
                truncated_score(region.target_fine.tree, pts, tau) * excluded,
                fitness,
                rmse,
                time.perf_counter() - t_begin,
                t,
            )
        )


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


def confirmed(
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


def distinct_ranked(
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


def flips(model: PreparedModel) -> list[tuple[str, Mat4]]:
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


def moment_candidates(model: PreparedModel, cluster: Points) -> list[Mat4]:
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


def _start_candidates(pool: CandidatePool, inputs: PoseInputs) -> None:
    """First-round starts independent of descriptors: the previous pose, as it stood and
    set on the cluster (:func:`previous_on_cluster`), the model standing as the library
    gives it, set on the cluster (:func:`upright_on_cluster`, unless the previous pose
    already stands so), then the four principal-axis alignments of what of the cluster
    stands above the support."""
    if inputs.previous is not None:
        pool.polish(inputs.previous, "previous pose", time.perf_counter())
    cluster = inputs.cluster
    if cluster is not None:
        # the axes of what stands above the support: floor smeared around an object's
        # foot tilts and shifts a flat object's axes
        standing = cluster
        support, band = pool.ctx.region.support, pool.ctx.region.band_m
        if support is not None:
            above = cluster[cluster @ support[:3] + support[3] > band]
            standing = above if len(above) >= 10 else cluster
        for k, init in enumerate(previous_on_cluster(pool.ctx.model, inputs, standing)):
            pool.polish(init, f"previous turned {k}", time.perf_counter())
        if inputs.previous is None or not pool.ctx.upright(inputs.previous):
            for k, init in enumerate(upright_on_cluster(pool.ctx.model, inputs, standing)):
                pool.polish(init, f"upright turned {k}", time.perf_counter())
        for k, init in enumerate(moment_candidates(pool.ctx.model, standing)):
            pool.polish(init, f"cluster axes {k}", time.perf_counter())


def _turned_on_cluster(
    model: PreparedModel, rotation: NDArray[np.float64], up: NDArray[np.float64], standing: Points
) -> list[Mat4]:
    """The (3, 3) ``rotation`` turned about the unit ``up`` in :data:`PREVIOUS_TURNS` steps,
    each set with the model's centre over the (K ≥ 1, 3) ``standing`` points' mean and its
    lowest point at their lowest (env frame, metres)."""
    mean, lowest = standing.mean(axis=0), np.min(standing @ up)
    out = []
    for k in range(PREVIOUS_TURNS):
        turn = rotation_about_unit_axis(up, 2.0 * np.pi * k / PREVIOUS_TURNS)
        r = turn @ rotation
        across = mean - r @ model.centre_object
        across -= (across @ up) * up
        lift = float(lowest - np.min(model.points @ r.T @ up))
        out.append(make_rigid(r, across + lift * up))
    return out


def previous_on_cluster(model: PreparedModel, inputs: PoseInputs, standing: Points) -> list[Mat4]:
    """The previous pose's orientation set on the (K, 3) ``standing`` cluster points and
    turned about the up axis (:func:`_turned_on_cluster`): where a moved object, slid or
    carried and set down on the same face, now stands (the previous pose itself lies where
    it stood before). [] without a previous pose or standing points."""
    if inputs.previous is None or len(standing) == 0:
        return []
    return _turned_on_cluster(model, inputs.previous[:3, :3], inputs.up, standing)


def upright_on_cluster(model: PreparedModel, inputs: PoseInputs, standing: Points) -> list[Mat4]:
    """The model standing on its library up (``model.up_object`` turned onto ``inputs.up``)
    set on the (K, 3) ``standing`` cluster points and turned about the up axis
    (:func:`_turned_on_cluster`): an object set down as it is made to stand, which the
    descriptors can miss where its scan fits better upside down (a mug whose opening
    stereo closed). [] without standing points."""
    if len(standing) == 0:
        return []
    return _turned_on_cluster(model, rotation_onto(model.up_object, inputs.up), inputs.up, standing)


def _ransac_candidates(pool: CandidatePool, round_: int) -> None:
    """This round's RANSAC seeds, scene → model (every visible scene point has its match on
    the model, while model points on the hidden side only add false matches); stops after
    ``min_seeds`` once two starts agree on the best candidate."""
    m, region, o = pool.ctx.model, pool.ctx.region, pool.ctx.options
    v = m.voxel_m
    if len(region.down.points) < 3:
        return
    f_model = REG.Feature()
    f_model.data = np.ascontiguousarray(m.fpfh.T)
    f_scene = REG.Feature()
    f_scene.data = np.ascontiguousarray(region.fpfh.T)
    checkers = [
        REG.CorrespondenceCheckerBasedOnEdgeLength(o.edge_length_check),
        REG.CorrespondenceCheckerBasedOnDistance(o.ransac_distance_voxels * v),
    ]
    for k in range(round_ * o.n_seeds, (round_ + 1) * o.n_seeds):
        if k - round_ * o.n_seeds >= o.min_seeds and confirmed(
            pool.trials, m.symmetry, m.diameter_m, m.centre_object
        ):
            break  # two independent starts already agree on the best candidate
        tk = time.perf_counter()
        with seeded_open3d(o.seed * 1000 + k):
            res = REG.registration_ransac_based_on_feature_matching(
                region.down,
                pool.model_features,
                f_scene,
                f_model,
                False,
                o.ransac_distance_voxels * v,
                REG.TransformationEstimationPointToPoint(False),
                3,
                checkers,
                REG.RANSACConvergenceCriteria(o.ransac_max_iterations, o.ransac_confidence),
            )
        if len(res.correspondence_set) >= 3:
            t_res = np.asarray(res.transformation, dtype=np.float64)
            pool.polish(invert_rigid(t_res), f"ransac seed {k}", tk)


def _flip_candidates(pool: CandidatePool) -> None:
    """The best ``n_flip_bases`` distinct candidates not turned yet, turned by :func:`flips`:
    RANSAC on a partial view often gets an elongated object's axes right but its ends
    swapped."""
    m = pool.ctx.model
    ranked = distinct_ranked(pool.trials, m.symmetry, m.diameter_m, m.centre_object)
    for base in ranked[: pool.ctx.options.n_flip_bases]:
        if id(base) in pool.flipped:
            continue
        pool.flipped.add(id(base))
        for name, flip in flips(m):
            pool.polish(base.env_from_object @ flip, f"{base.source} + {name}", time.perf_counter())


def add_round_candidates(pool: CandidatePool, round_: int, inputs: PoseInputs) -> None:
    """Step 2 for round ``round_`` (0-based): starts (first round only), RANSAC seeds, then
    flips. RegistrationError when no candidate explains any of the scene region."""
    if round_ == 0:
        _start_candidates(pool, inputs)
    _ransac_candidates(pool, round_)
    trials = pool.trials
    if not trials or max(t.score for t in trials) <= 0.0:
        region = pool.ctx.region
        raise RegistrationError(
            f"no registration candidate explains the scene region ({len(trials)} candidates, "
            f"{region.n_points} points within {region.radius_m:.3f} m)"
        )
    _flip_candidates(pool)
