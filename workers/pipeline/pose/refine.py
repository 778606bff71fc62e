"""Step 3 of pose estimation: refinement of the best distinct candidates.

The best ``n_refine`` distinct candidates not refined yet (across rounds) are refined by
multi-scale point-to-plane ICP on a ``v/2`` subsample of the model (``1.5v`` → ``0.25v``,
pairs with incompatible normals ignored) and re-scored at ``fine_score_voxels`` on the
model points a camera could see (not those resting on the support; sunk ones count), where
near-symmetric alternatives separate; an upside-down best is also refined turned upright.
The winner gets a last ICP on every model point and then a fit of the scan onto them
(:func:`~workers.pipeline.pose.fit.fit_scene_to_model`, robust, scene to model), kept
unless it turned the ICP's pose by more than ``max_final_turn_deg``; it is lifted onto its
support when it sank into it, and set flat on it when it touches it
(within ``rest_max_tilt_deg``: verifiable; within ``max_set_down_tilt_deg``: unverified;
the turn and shift across it refitted unless that lowers the fitness, a flat object's to
its outline seen from above, :mod:`~workers.pipeline.pose.top_view`); that turn and the
rotation the residual level hides (:func:`~workers.pipeline.pose.fit.rotation_slack_deg`)
say how well the scan holds it. Its near-ties (refined poses scoring almost as well) are
finished the same way: one that comes to the winner's pose is no rival, and among flat
ones the outline seen from above may settle which face and turn the scan shows.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from workers.pipeline.geometry import Mat4, Points, rotation_angle_deg, transform_points
from workers.pipeline.model import make_cloud
from workers.pipeline.model.symmetry_group import symmetric_pose_error
from workers.pipeline.pose.candidates import (
    CandidatePool,
    FitContext,
    distinct_pose,
    distinct_ranked,
    flips,
)
from workers.pipeline.pose.fit import (
    ModelSurface,
    fit_scene_to_model,
    fitness_and_rmse,
    hull_normals,
    icp_point_to_plane,
    lowest_height,
    normalised,
    out_of_support,
    plane_beyond,
    resting_turn,
    rotation_slack_deg,
    truncated_score,
)
from workers.pipeline.pose.result import Trial
from workers.pipeline.pose.top_view import fit_top_view, outline_costs, stands_flat


@dataclass(frozen=True)
class Refined:
    """One refined candidate: its fine ``score``, refined ``env_from_object`` and the
    :class:`Trial` it started from."""

    score: float
    env_from_object: Mat4
    trial: Trial


@dataclass(frozen=True)
class Refinement:
    """The winner of one round: ``env_from_object`` after the last fits and the support
    steps, its fine ``score``, the ``runner_up`` (fine score of the best other refined pose
    still distinct from it when finished as it was, 0 if none; none when the outline
    settled the near-ties), ``fitness`` and ``inlier_rmse_m`` of every model point within
    ``inlier_distance_m`` of the scene, the ``best`` trial it came from and the
    ``rotation_slack_deg`` its residual level hides, and ``final_turn_deg``, how far the
    scan-to-model fit turned the ICP's pose, or the refit on the support turned the pose
    set flat, whichever is more, modulo symmetry (both 0 when not computed), and
    ``tipped_deg``, the tilt taken out when it touched its support on nothing it could rest
    on (0 otherwise); ``others``: every other refined pose, best first, a near-tie finished
    as the winner was (:meth:`Refiner._finish`) at its finished pose;
    ``settled_by_outline``: (its outline's cost per scan point, the least near-tie's) when
    the outline settled the near-ties of a flat pose (:meth:`Refiner._by_outline`), else
    None; ``righted``: the upright rule stood the winner up over a better-scoring
    upside-down pose (:meth:`Refiner._winner`)."""

    env_from_object: Mat4
    score: float
    runner_up: float
    fitness: float
    inlier_rmse_m: float
    inlier_distance_m: float
    best: Trial
    rotation_slack_deg: float = 0.0
    final_turn_deg: float = 0.0
    tipped_deg: float = 0.0
    others: tuple[Refined, ...] = ()
    settled_by_outline: tuple[float, float] | None = None
    righted: bool = False


@dataclass(frozen=True)
class _Finished:
    """A refined pose after the winner's last steps (:meth:`Refiner._finish`): its
    ``env_from_object`` and the figures :class:`Refinement` reports of it (``evaluated``:
    its :meth:`Refiner.evaluate` when already computed)."""

    refined: Refined
    env_from_object: Mat4
    rotation_slack_deg: float
    final_turn_deg: float
    tipped_deg: float
    evaluated: tuple[float, float] | None


@dataclass
class Refiner:
    """Refinement state across rounds (mutable): every ``refined`` candidate so far, best
    first after each round, the ids of the trials already refined and of the refined poses
    already turned upright (:meth:`_turn_upright`), and the refined poses already finished
    (:meth:`_finish`) by id."""

    ctx: FitContext
    mid_points: Points
    mid_normals: Points
    surface: ModelSurface
    rest_bases: Points
    hull_faces: Points
    refined: list[Refined] = field(default_factory=list)
    refined_ids: set[int] = field(default_factory=set)
    turned_ids: set[int] = field(default_factory=set)
    finished: dict[int, _Finished] = field(default_factory=dict)

    @classmethod
    def create(cls, ctx: FitContext) -> Refiner:
        """A refiner with the model's ``v/2`` subsample."""
        m = ctx.model
        model_mid = make_cloud(m.points, m.normals, m.colors).voxel_down_sample(m.voxel_m / 2)
        return cls(
            ctx,
            np.asarray(model_mid.points),
            normalised(np.asarray(model_mid.normals)),
            ModelSurface(m.points, m.normals),
            # the base the library gives the model resting on under each symmetry element
            # (identity first; a can stands on either end)
            np.stack([-r[:3, :3] @ m.up_object for r in m.symmetry.rotations]),
            hull_normals(m.points, m.centre_object),
        )

    def _refine(self, trial: Trial) -> Refined:
        """Multi-scale ICP of one trial on the mid-subsample points a camera could see from
        the pose each scale starts at (:meth:`_in_view`, the points the score counts: the
        hidden underside, with no scan to pair with, would pull the fit), scored at the
        fine scale."""
        o, v = self.ctx.options, self.ctx.model.voxel_m
        target = self.ctx.region.target_fine
        pose = trial.env_from_object
        for scale in o.icp_scales_voxels:
            posed = transform_points(pose, self.mid_points)
            seen = self._in_view(posed, self.mid_normals, pose[:3, :3])
            pose = icp_point_to_plane(
                self.mid_points[seen],
                self.mid_normals[seen],
                target,
                pose,
                scale * v,
                o.icp_max_iterations,
            )
        return Refined(self.score(pose), pose, trial)

    def score(self, env_from_object: Mat4) -> float:
        """The fine score of a pose: :func:`truncated_score` at ``fine_score_voxels`` of the
        mid-sample model points a camera could see (:meth:`_in_view`) times the
        :meth:`FitContext.exclusion` of them all."""
        o, v = self.ctx.options, self.ctx.model.voxel_m
        posed_mid = transform_points(env_from_object, self.mid_points)
        in_view = posed_mid[self._in_view(posed_mid, self.mid_normals, env_from_object[:3, :3])]
        return truncated_score(
            self.ctx.region.target_fine.tree, in_view, o.fine_score_voxels * v
        ) * self.ctx.exclusion(posed_mid)

    def _in_view(
        self, posed: Points, normals_object: Points, rotation: NDArray[np.float64]
    ) -> NDArray[np.bool_]:
        """(N,) mask of the (N, 3) model points posed with (3, 3) ``rotation`` (their (N, 3)
        ``normals_object``, object frame) that a camera could see: not on the support
        (within its band: the scene has no point there) nor facing down at it within two
        voxels (under an object resting there no camera looks: a mug upright hides its
        base, upside down only its rim); all of them when fewer than 10 are left. Points
        sunk below the support's own points (half a band under the plane) stay: a pose does
        not hide what it fails to explain in the floor."""
        region = self.ctx.region
        if region.support is None:
            return np.ones(len(posed), dtype=bool)
        n = region.support[:3]
        height = posed @ n + region.support[3]
        facing = normals_object @ rotation.T @ n
        hidden = (height >= -region.band_m / 2) & (
            (height <= region.band_m) | ((facing < -0.7) & (height < 2 * self.ctx.model.voxel_m))
        )
        return ~hidden if np.count_nonzero(~hidden) >= 10 else np.ones(len(posed), dtype=bool)

    def _turn_upright(self) -> None:
        """When the best refined pose is upside down, its turns (:func:`flips`) that stand
        it upright are refined too, once per pose: a flat object's smeared scan fits its
        other face almost as well, and no start may have come near its upright pose."""
        top = self.refined[0]
        if self.ctx.upright(top.env_from_object) or id(top) in self.turned_ids:
            return
        self.turned_ids.add(id(top))
        t = top.trial
        for name, flip in flips(self.ctx.model):
            pose = top.env_from_object @ flip
            if self.ctx.upright(pose):
                turned = Trial(f"{t.source} + {name}", t.score, t.fitness, t.inlier_rmse_m, 0, pose)
                self.refined.append(self._refine(turned))
        self.refined.sort(key=lambda r: -r.score)

    def _winner(self) -> Refined:
        """The best refined pose, unless it is upside down (model up away from the
        environment's) and an upright one that rests on the support (its lowest point
        within ``max_sink_m`` of the plane, when there is one) scores at least
        ``upright_ratio`` × it: the scan cannot tell those apart, and a library model is
        given resting on its base. Such a pose stays unverified (its rival counts as the
        runner-up)."""
        top = self.refined[0]
        if self.ctx.upright(top.env_from_object):
            return top
        o, support = self.ctx.options, self.ctx.region.support

        def rests(pose: Mat4) -> bool:
            if support is None:
                return True
            posed = transform_points(pose, self.mid_points)
            return abs(lowest_height(posed, support)) <= o.max_sink_m

        return next(
            (
                r
                for r in self.refined
                if r.score >= o.upright_ratio * top.score
                and self.ctx.upright(r.env_from_object)
                and rests(r.env_from_object)
            ),
            top,
        )

    def _at_rest(
        self, pose: Mat4, scene: Points, reach_m: float
    ) -> tuple[Mat4, float, float, tuple[float, float] | None]:
        """``pose`` set flat on its support when it touches it: its lowest point within
        ``max_sink_m`` of the plane (which reaches beyond it). It is set on its base (−up of
        the model: the library gives models resting on it), else on the hull face nearest
        the plane that holds its centre above it: within ``rest_max_tilt_deg`` of flat, else
        within ``max_set_down_tilt_deg`` (it touches the plane on nothing it could rest on,
        so it would fall over: the scan, not the object, is tilted, as a hollow bowl's is;
        tilted further, something holds it). That face is turned flat about the object's
        centre, the turn about the plane's normal and the shift across it refitted by the
        scan-to-model fit on the (M, 3) ``scene`` points (kept unless it lowers the fitness,
        :meth:`evaluate`: then the pose set flat stays; a flat object's, :meth:`_is_flat`,
        by its outline seen from above, :meth:`_seen_from_above`), and the lowest point set
        on the plane. Objects stand on their supports: the plane, fitted on thousands of floor
        points, holds the tilt and height better than the object's own few hundred.
        Otherwise ``pose`` unchanged. Also returns, degrees, how far the refit turned it
        (beyond ``max_final_turn_deg`` the scan does not hold that turn) and the tilt taken
        out beyond the window (0 within it); the caller counts either against
        verification; and the returned pose's :meth:`evaluate` when it was computed here
        (None otherwise)."""
        m, o, support = self.ctx.model, self.ctx.options, self.ctx.region.support
        if support is None or o.rest_max_tilt_deg <= 0:
            return pose, 0.0, 0.0, None
        posed = transform_points(pose, m.points)
        on_support = self.ctx.region.on_support
        if abs(lowest_height(posed, support)) > o.max_sink_m or not plane_beyond(
            posed, on_support, 2 * m.voxel_m
        ):
            return pose, 0.0, 0.0, None
        faces = (pose[:3, :3], self.rest_bases, self.hull_faces, support[:3])
        turn = resting_turn(*faces, o.rest_max_tilt_deg)
        tipped_deg = 0.0
        if turn is None:
            if o.max_set_down_tilt_deg <= o.rest_max_tilt_deg:
                return pose, 0.0, 0.0, None
            turn = resting_turn(*faces, o.max_set_down_tilt_deg)
            if turn is None:
                return pose, 0.0, 0.0, None
            tipped_deg = rotation_angle_deg(turn)
        centre = pose[:3, :3] @ m.centre_object + pose[:3, 3]
        flat = np.eye(4)
        flat[:3, :3] = turn @ pose[:3, :3]
        flat[:3, 3] = turn @ (pose[:3, 3] - centre) + centre
        rested, _ = fit_scene_to_model(
            self.surface, scene, flat, reach_m, o.final_max_iterations, plane_normal=support[:3]
        )
        for p in (flat, rested):
            p[:3, 3] -= lowest_height(transform_points(p, m.points), support) * support[:3]
        if self._is_flat(flat):
            # a flat object's fitness barely tells its turns apart: its outline does
            seen = self._seen_from_above(flat, rested)
            seen_turn = symmetric_pose_error(seen, flat, m.symmetry, m.centre_object)[1]
            return seen, seen_turn, tipped_deg, None
        refit_turn = symmetric_pose_error(rested, flat, m.symmetry, m.centre_object)[1]
        # a refit that lowers the fitness slid off what the scan holds (a tall object's
        # weak turn): the pose set flat stays
        refit, as_set = self.evaluate(rested), self.evaluate(flat)
        if refit[0] >= as_set[0]:
            return rested, refit_turn, tipped_deg, refit
        return flat, refit_turn, tipped_deg, as_set

    def _is_flat(self, env_from_object: Mat4) -> bool:
        """Whether the model posed on the support stands at most
        ``top_view_max_height_ratio`` × its diameter tall above it."""
        m, support = self.ctx.model, self.ctx.region.support
        if support is None:
            return False
        ratio = self.ctx.options.top_view_max_height_ratio
        return stands_flat(m.points, m.diameter_m, env_from_object, support[:3], ratio)

    def _seen_from_above(self, *starts: Mat4) -> Mat4:
        """The in-plane fit of the outline seen from above
        (:func:`~workers.pipeline.pose.top_view.fit_top_view`) from the poses ``starts``
        resting on the support."""
        m, o, region = self.ctx.model, self.ctx.options, self.ctx.region
        assert region.support is not None
        return fit_top_view(
            m,
            starts,
            region.support,
            region.target_fine.points,
            region.on_support,
            o.top_view_reach_voxels * m.voxel_m,
            o.top_view_window_voxels * m.voxel_m,
        )

    @property
    def inlier_distance_m(self) -> float:
        """The inlier distance of ``fitness``, metres: ``inlier_voxels`` or
        ``inlier_spacings`` × the scan's spacing, the larger, at most
        ``max_inlier_distance_m``."""
        o = self.ctx.options
        reach = max(
            o.inlier_voxels * self.ctx.model.voxel_m,
            o.inlier_spacings * self.ctx.region.spacing_m,
        )
        return min(reach, o.max_inlier_distance_m)

    def evaluate(self, env_from_object: Mat4) -> tuple[float, float]:
        """(fitness, inlier RMSE in metres) of ``env_from_object``: the share of every model
        point with a scene point within :attr:`inlier_distance_m`, and those distances'
        RMS."""
        posed = transform_points(env_from_object, self.ctx.model.points)
        return fitness_and_rmse(self.ctx.region.target_fine.tree, posed, self.inlier_distance_m)

    def _picks(self, distinct: list[Trial]) -> list[Trial]:
        """The trials to refine this round: the best ``n_refine`` of ``distinct`` (best
        first) not refined yet, and the best one the other way up from the best (a hollow
        object whose opening the scan closes, or a flat one, fits almost as well on its
        other face) when it is neither."""
        picks = [t for t in distinct if id(t) not in self.refined_ids][: self.ctx.options.n_refine]
        if distinct:
            up = self.ctx.upright(distinct[0].env_from_object)
            other = next((t for t in distinct if self.ctx.upright(t.env_from_object) != up), None)
            taken = self.refined_ids | {id(t) for t in picks}
            if other is not None and id(other) not in taken:
                picks.append(other)
        return picks

    def _finish(self, refined: Refined) -> _Finished:
        """The last steps of a refined pose (once per pose): ICP on every model point a camera
        could see at it (:meth:`_in_view`), the scan-to-model fit (kept unless it turned the
        ICP's pose by more than ``max_final_turn_deg``), lifted out of its support and set
        at rest on it (:meth:`_at_rest`)."""
        if id(refined) in self.finished:
            return self.finished[id(refined)]
        m, o, region = self.ctx.model, self.ctx.options, self.ctx.region
        v = m.voxel_m
        slack = turn = 0.0
        start = refined.env_from_object
        seen = self._in_view(transform_points(start, m.points), m.normals, start[:3, :3])
        icp_pose = icp_point_to_plane(
            m.points[seen],
            m.normals[seen],
            region.target_fine,
            start,
            o.icp_scales_voxels[-1] * v,
            o.icp_max_iterations,
        )
        env_from_object = icp_pose
        reach = min(o.final_reach_voxels * v, o.max_inlier_distance_m)
        # the scan near the pose (within two reaches of the posed model) is all the final
        # fits can pair
        near, _ = cKDTree(transform_points(icp_pose, m.points)).query(
            region.target_fine.points, distance_upper_bound=2 * reach
        )
        scene = region.target_fine.points[np.isfinite(near)]
        if o.final_fit == "scene_to_model":
            fitted, weights = fit_scene_to_model(
                self.surface, scene, icp_pose, reach, o.final_max_iterations
            )
            free_axis = m.symmetry.axis if m.symmetry.kind == "continuous" else None
            slack = rotation_slack_deg(self.surface, scene, weights, fitted, free_axis)
            # two estimators with different weaknesses (model onto scan with the scan's
            # normals; scan onto model, robust): where they disagree by more than
            # max_final_turn_deg the scan does not settle the rotation, the pose is not
            # verified and the ICP's is kept (the closer of the two on the tuning set)
            turn = symmetric_pose_error(fitted, icp_pose, m.symmetry, m.centre_object)[1]
            if turn <= o.max_final_turn_deg:
                env_from_object = fitted
        env_from_object = out_of_support(
            env_from_object, m.points, region.support, region.on_support, o.max_sink_m, 2 * v
        )
        env_from_object, rest_turn, tipped, evaluated = self._at_rest(env_from_object, scene, reach)
        done = _Finished(refined, env_from_object, slack, max(turn, rest_turn), tipped, evaluated)
        self.finished[id(refined)] = done
        return done

    def refit(self, start: Mat4, like: Refinement) -> Refinement:
        """``like`` with its pose replaced by ``start`` (its equivalent under the model's
        discrete symmetry) finished as a winner is (:meth:`_finish`: the fine ICP, the
        last fit, at rest), and that pose's fitness, slack, turns and tilt: a scanned
        model repeats only nearly, so the group element that carried the pose there
        leaves it a little off, not far (the coarse ICP scales would let it slide).
        Its score, runner-up and others stay ``like``'s."""
        trial = Trial("equivalent", like.score, like.fitness, like.inlier_rmse_m, 0, start)
        done = self._finish(Refined(like.score, start, trial))  # the score is like's
        fitness, rmse = done.evaluated or self.evaluate(done.env_from_object)
        return replace(
            like,
            env_from_object=done.env_from_object,
            fitness=fitness,
            inlier_rmse_m=rmse,
            rotation_slack_deg=done.rotation_slack_deg,
            final_turn_deg=done.final_turn_deg,
            tipped_deg=done.tipped_deg,
        )

    def _distinct(self, a: Mat4, b: Mat4) -> bool:
        """:func:`distinct_pose` for this model."""
        m = self.ctx.model
        return distinct_pose(a, b, m.symmetry, m.diameter_m, centre=m.centre_object)

    def _by_outline(self, contenders: list[_Finished]) -> tuple[_Finished, float, float] | None:
        """Of distinct ``contenders`` (the winner first, then its near-ties) all resting
        flat on the support (:meth:`_is_flat`), the one the outline seen from above chooses
        (:func:`~workers.pipeline.pose.top_view.outline_costs`, per scan point: a flat
        object's fine scores barely tell its faces apart, its outline does): the least-cost
        one when the winner costs more than ``outline_settle_ratio`` × it, else the winner;
        with its cost and the least of the others'. None when one is not flat, no scan
        point is near them, or ``outline_settle_ratio`` is 0."""
        m, o, region = self.ctx.model, self.ctx.options, self.ctx.region
        ratio = o.outline_settle_ratio
        if region.support is None or ratio <= 0:
            return None
        if not all(self._is_flat(c.env_from_object) for c in contenders):
            return None
        costs = outline_costs(
            m,
            [c.env_from_object for c in contenders],
            region.support,
            region.target_fine.points,
            region.on_support,
            o.top_view_reach_voxels * m.voxel_m,
            o.top_view_window_voxels * m.voxel_m,
        )
        least = int(np.argmin(costs))
        if not np.isfinite(costs[least]):
            return None
        chosen = least if costs[0] > ratio * costs[least] else 0
        other = min(c for i, c in enumerate(costs) if i != chosen)
        return contenders[chosen], costs[chosen], other

    def round(self, pool: CandidatePool) -> Refinement:
        """Step 3 for one round: refine the new best distinct candidates of ``pool``, then
        finish the best refined pose so far and its near-ties (fine score above
        ``max_runner_up_ratio`` × its own) the same way; a near-tie that comes to the same
        pose is none, and a flat object's outline may choose among the rest and settle
        them when every other costs more than ``outline_settle_ratio`` × the chosen
        (:meth:`_by_outline`)."""
        m, o = self.ctx.model, self.ctx.options
        distinct = distinct_ranked(pool.trials, m.symmetry, m.diameter_m, m.centre_object)
        for t in self._picks(distinct):
            self.refined_ids.add(id(t))
            self.refined.append(self._refine(t))
        self.refined.sort(key=lambda r: -r.score)
        self._turn_upright()
        best = self._winner()
        won = self._finish(best)
        near = [
            r
            for r in self.refined
            if r is not best
            and r.score > o.max_runner_up_ratio * best.score
            and self._distinct(r.env_from_object, won.env_from_object)
        ]
        contenders = [won, *(self._finish(r) for r in near)]
        ties = [c for c in contenders[1:] if self._distinct(c.env_from_object, won.env_from_object)]
        by_outline = self._by_outline([won, *ties]) if ties else None
        settled: tuple[float, float] | None = None
        if by_outline is not None:
            won, cost, rival_cost = by_outline
            if rival_cost > o.outline_settle_ratio * cost:
                settled = (cost, rival_cost)
        contending = {id(c.refined): c for c in contenders}

        def rival(r: Refined) -> bool:
            if r is won.refined or (settled and id(r) in contending):
                return False
            pose = contending[id(r)].env_from_object if id(r) in contending else r.env_from_object
            return self._distinct(pose, won.env_from_object)

        fitness, rmse = won.evaluated or self.evaluate(won.env_from_object)
        return Refinement(
            env_from_object=won.env_from_object,
            score=won.refined.score,
            runner_up=next((r.score for r in self.refined if rival(r)), 0.0),
            fitness=fitness,
            inlier_rmse_m=rmse,
            inlier_distance_m=self.inlier_distance_m,
            best=won.refined.trial,
            rotation_slack_deg=won.rotation_slack_deg,
            final_turn_deg=won.final_turn_deg,
            tipped_deg=won.tipped_deg,
            # a near-tie finished above is given as finished: the tie-breaks after the pose
            # step compare it with the winner, which is finished too
            others=tuple(
                replace(r, env_from_object=contending[id(r)].env_from_object)
                if id(r) in contending
                else r
                for r in self.refined
                if r is not won.refined
            ),
            settled_by_outline=settled,
            righted=best is not self.refined[0],
        )
