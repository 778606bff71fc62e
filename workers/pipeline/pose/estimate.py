"""Estimate one object's pose in the environment: ``env_from_object`` (4×4, metres).

Input: a :class:`~workers.pipeline.model.PreparedModel` (object frame) and the scene cloud
(environment frame, metres) with the changed cluster's points or centre. The steps, one
module each:

1. :mod:`~workers.pipeline.pose.crop`: the scene region around the cluster, its support
   plane removed, downsampled at the model's feature voxel ``v`` and described by FPFH;
2. :mod:`~workers.pipeline.pose.candidates`: global candidates (previous pose, cluster
   axes, FPFH + RANSAC seeds, 180° flips and near-symmetries), each polished by a short ICP
   and scored;
3. :mod:`~workers.pipeline.pose.refine`: the best distinct candidates refined by
   multi-scale point-to-plane ICP and re-scored at a fine scale;
4. :mod:`~workers.pipeline.pose.verify`: fitness, cluster coverage and the
   best distinct alternative decide ``verified``; while not verified, steps 2-4 run again
   with new seeds, up to ``max_rounds`` rounds;
5. :mod:`~workers.pipeline.pose.canonical`: one canonical pose among a symmetric object's
   equivalents; one that a discrete group element carried the fit to is fitted again
   (a scanned shape repeats only nearly).

Seeded by ``PoseOptions.seed`` and repeatable: on one machine the same inputs give the
same pose (the feature RANSAC runs on one Open3D thread). Raises RegistrationError when
no candidate is plausible, InputError/ShapeError for unusable inputs.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, replace

from numpy.typing import ArrayLike

from workers.pipeline.compare.visibility import DepthMap
from workers.pipeline.errors import InputError, ShapeError
from workers.pipeline.geometry import Mat4, rotation_angle_deg
from workers.pipeline.model import PreparedModel
from workers.pipeline.pose.candidates import CandidatePool, FitContext, add_round_candidates
from workers.pipeline.pose.canonical import CanonicalPose, canonical_pose, colour_agreement
from workers.pipeline.pose.crop import PoseInputs, SceneCloud, check_inputs, crop_scene
from workers.pipeline.pose.options import FINAL_FITS, POSE_PRESETS, PoseOptions
from workers.pipeline.pose.refine import Refined, Refinement, Refiner
from workers.pipeline.pose.result import Alternative, PoseResult, Trial
from workers.pipeline.pose.verify import FitVerification, verify_fit


@dataclass(frozen=True)
class _Fit:
    """What steps 2-4 leave: the last round's ``refinement`` and its ``verification``, every
    candidate ``trials``, the refined ``alternatives`` to the winner, best first, and the
    ``refiner`` that made them."""

    refinement: Refinement
    verification: FitVerification
    trials: tuple[Trial, ...]
    alternatives: tuple[Refined, ...]
    refiner: Refiner


def _fit_rounds(ctx: FitContext, inputs: PoseInputs, timings: dict[str, float]) -> _Fit:
    """Steps 2-4, repeated with new seeds while the pose is not verified."""
    pool = CandidatePool.create(ctx)
    refiner = Refiner.create(ctx)
    timings["refine"] = 0.0
    for round_ in range(ctx.options.max_rounds):
        t0 = time.perf_counter()
        add_round_candidates(pool, round_, inputs)
        timings["global"] = timings.get("global", 0.0) + time.perf_counter() - t0
        t0 = time.perf_counter()
        fit = refiner.round(pool)
        timings["refine"] += time.perf_counter() - t0
        verdict = verify_fit(fit, ctx.model.points, inputs.cluster, ctx.model.voxel_m, ctx.options)
        if verdict.verified:
            break
    timings["rounds"] = float(round_ + 1)
    return _Fit(fit, verdict, tuple(pool.trials), fit.others, refiner)


def _published(
    ctx: FitContext, inputs: PoseInputs, rounds: _Fit
) -> tuple[CanonicalPose, Refinement, FitVerification]:
    """Step 5: the canonical pose of the last round's fit, with the fit and verification
    it is published with."""
    model, options = ctx.model, ctx.options
    fit, verdict = rounds.refinement, rounds.verification

    def colour(pose: Mat4) -> float:
        return colour_agreement(model, pose, ctx.region.target_fine, fit.inlier_distance_m)

    canonical = canonical_pose(
        fit.env_from_object, model, inputs.up, inputs.previous, colour, options.colour_margin
    )
    if model.symmetry.kind == "discrete" and not _same_rotation(canonical.env_from_object, fit):
        # the equivalent chosen is the fit carried by a group element of a shape that
        # repeats only nearly: fitted again from there, and verified as fitted
        fit = rounds.refiner.refit(canonical.env_from_object, fit)
        verdict = verify_fit(fit, model.points, inputs.cluster, model.voxel_m, options)
        pose = fit.env_from_object
        others = tuple(pose @ s for s in model.symmetry.rotations[1:])
        canonical = replace(canonical, env_from_object=pose, equivalents=others)
    return canonical, fit, verdict


def _same_rotation(pose: Mat4, fit: Refinement) -> bool:
    """Whether ``pose`` turns the object as ``fit``'s pose does (within 0.1°)."""
    return rotation_angle_deg(pose[:3, :3].T @ fit.env_from_object[:3, :3]) < 0.1


def _unsettled(model: PreparedModel, chosen_by: str) -> tuple[str, ...]:
    """Why a pose cannot be verified although it fits: an object whose shape repeats under
    a discrete symmetry but whose appearance does not (a label, wood grain) is right only
    as the equivalent colour chose, and so is which end of a round one (a can) is up; any
    other choice is a guess among equally good fits."""
    symmetry = model.symmetry
    if not symmetry.appearance_breaks or chosen_by == "colour":
        return ()
    n = len(symmetry.rotations)
    if symmetry.kind == "discrete":
        return (f"colour does not settle which of its {n} symmetric equivalents it is",)
    if symmetry.kind == "continuous" and n > 1:
        return ("colour does not settle which end of it is up",)
    return ()


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
    if not isinstance(scene, SceneCloud):
        raise ShapeError("scene must be a SceneCloud (use SceneCloud.create)")
    inputs = check_inputs(cluster_points_env, centre_env, previous_env_from_object, up_env)
    if options.max_rounds < 1 or options.n_seeds < 0:
        raise InputError("PoseOptions needs max_rounds ≥ 1 and n_seeds ≥ 0")
    if options.final_fit not in FINAL_FITS:
        raise InputError(
            f"PoseOptions.final_fit must be one of {FINAL_FITS}, got {options.final_fit!r}"
        )
    region = crop_scene(model, scene, inputs, options)
    timings = {
        "support_removed": float(region.support_removed),
        "prepare": time.perf_counter() - t_start,
    }
    ctx = FitContext(model, region, free_space, options, inputs.up)
    rounds = _fit_rounds(ctx, inputs, timings)
    canonical, fit, verdict = _published(ctx, inputs, rounds)
    rejections = verdict.rejections + _unsettled(model, canonical.chosen_by)
    timings["total"] = time.perf_counter() - t_start
    return PoseResult(
        env_from_object=canonical.env_from_object,
        fitness=fit.fitness,
        inlier_rmse_m=fit.inlier_rmse_m,
        inlier_distance_m=fit.inlier_distance_m,
        score=fit.score,
        runner_up_score=fit.runner_up,
        cluster_coverage=verdict.cluster_coverage,
        verified=not rejections,
        rejections=rejections,
        ambiguous=model.symmetry.is_symmetric,
        equivalent_poses=canonical.equivalents,
        symmetry_axis_env=canonical.axis_env,
        symmetry_origin_env=canonical.origin_env,
        chosen_by=canonical.chosen_by,
        source=fit.best.source,
        trials=rounds.trials,
        n_scene_points=region.n_points,
        alternatives=tuple(Alternative(r.score, r.env_from_object) for r in rounds.alternatives),
        rotation_slack_deg=fit.rotation_slack_deg,
        final_turn_deg=fit.final_turn_deg,
        settled_by_outline=fit.settled_by_outline,
        righted=fit.righted,
        timings_s=timings,
    )
