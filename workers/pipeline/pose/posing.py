"""The pose step after a comparison: a 6-DoF pose for every identified object that appeared,
each checked by re-projection into the after capture's detections.

Shared by the comparison job (workers/comparison.py) and the benchmarks, so both pose the
same way. Pure: prepared models come in through ``load_model``; nothing is read from
storage here.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from workers.pipeline.compare.data import Camera, CaptureData
from workers.pipeline.compare.options import CompareOptions
from workers.pipeline.compare.results import Change, CompareResult
from workers.pipeline.compare.stage import render_depth_maps
from workers.pipeline.compare.visibility import DepthMap
from workers.pipeline.errors import PipelineError
from workers.pipeline.geometry import Mat4, transform_points
from workers.pipeline.model import PreparedModel
from workers.pipeline.model.symmetry_group import symmetric_pose_error
from workers.pipeline.pose.candidates import distinct_pose, upright
from workers.pipeline.pose.crop import SceneCloud
from workers.pipeline.pose.estimate import estimate_pose
from workers.pipeline.pose.fit import inlier_figures
from workers.pipeline.pose.options import PoseOptions, pose_options_from_json
from workers.pipeline.pose.photo_edges import CaptureSight, fit_photo_edges
from workers.pipeline.pose.result import CHOICE_FIGURES, PoseResult
from workers.pipeline.pose.top_view import turned_in_plane
from workers.pipeline.pose.verify import (
    FINAL_TURN_REASON,
    RUNNER_UP_REASON,
    ReprojectionCheck,
    reprojection_check,
    scene_distances,
    visible_fitness,
)
from workers.pipeline.threads import ordered_map

POSED_TYPES = frozenset({"added", "moved", "swapped"})
#: how much better (mean IoU with the detector's boxes) the chosen pose must re-project than
#: any distinct near-tie before the tie counts as settled
RIVAL_IOU_MARGIN = 0.1
#: how much larger the pose step's choice's visible fitness must be than any distinct
#: near-tie's before the tie counts as settled by what the cameras saw
RIVAL_SEEN_MARGIN = 0.04
#: how many times every other distinct near-tie's mean distance to the photos' edges must
#: exceed one's (each fitted to them alike) before the photos settle the tie for it
RIVAL_PHOTO_RATIO = 2.0
#: the photo fits started from the published pose turned either way by the two last fits'
#: disagreement must each end within this share of that turn of it for the photos to
#: settle the disagreement (their turn within ``max_final_turn_deg``): more than half way
#: back; photos that hold no turn leave a fit where it starts (1); lower settles fewer
PHOTO_BASIN_SHARE = 0.5
#: the environment's up: z (the markers' floor normal); the pose step and the box
#: tie-break below judge "upright" against it
UP_ENV = np.array([0.0, 0.0, 1.0])
Progress = Callable[[str, float], None]


def cameras_from_json(images: Mapping[str, Mapping[str, Any]]) -> tuple[Camera, ...]:
    """Cameras from a reconstruction's cameras.json ``{"images": {name: {"K", "width",
    "height", "env_from_cam", ...}}}`` (pass the ``images`` mapping), sorted by name;
    ``env_from_cam`` 4×4 metres, OpenCV axes."""
    return tuple(
        Camera(
            name=name,
            k=np.asarray(view["K"], dtype=np.float64),
            width=int(view["width"]),
            height=int(view["height"]),
            cam_from_env=np.linalg.inv(np.asarray(view["env_from_cam"], dtype=np.float64)),
        )
        for name, view in sorted(images.items())
    )


def _rivals(pose: PoseResult, model: PreparedModel, options: PoseOptions) -> list[Mat4]:
    """The refined alternatives that tie with the chosen pose (fine score above
    ``max_runner_up_ratio`` × the best) and are distinct from it modulo symmetry."""
    return [
        alt.env_from_object
        for alt in pose.alternatives
        if alt.score > options.max_runner_up_ratio * pose.score
        and distinct_pose(
            alt.env_from_object,
            pose.env_from_object,
            model.symmetry,
            model.diameter_m,
            centre=model.centre_object,
        )
    ]


def pose_change(
    change: Change,
    model: PreparedModel,
    scene: SceneCloud,
    sight: CaptureSight,
    class_id: int,
    options: PoseOptions,
) -> dict[str, Any]:
    """Pose, quality and centre of one change seen by the after capture's ``sight``; a
    failed registration is reported on the change (``verified: false`` with the reason),
    never dropped. Only a move's previous pose is used (a swap's is the replaced object's)."""
    after, depth_maps = sight.capture, sight.depth_maps
    previous = change.previous_env_from_object if change.type == "moved" else None
    try:
        pose = estimate_pose(
            model,
            scene,
            cluster_points_env=change.cluster.points_env,
            previous_env_from_object=previous,
            up_env=UP_ENV,
            free_space=depth_maps or (),
            options=options,
        )
    except PipelineError as exc:
        return {
            "pose": None,
            "pose_quality": {"verified": False, "reasons": [f"{exc.code}: {exc.detail}"]},
        }

    def check_of(env_from_object: Any) -> ReprojectionCheck:
        return reprojection_check(
            model.points, env_from_object, class_id, after.cameras, after.detections, depth_maps
        )

    seen_of = _visible_fitness_of(model, scene, depth_maps, pose.inlier_distance_m)

    chosen = pose.env_from_object
    check = check_of(chosen)
    quality = pose.quality_json() | {"chosen_by": pose.chosen_by}
    reasons = list(pose.rejections)
    rivals = _rivals(pose, model, options)
    if any(r.startswith(RUNNER_UP_REASON) for r in reasons):
        # A distinct pose fits the cloud almost as well (a near-symmetric object, a hammer
        # on either face). What the cameras saw of each pose (visible fitness) settles the
        # tie when it clearly prefers the pose step's choice; else the detector's boxes
        # choose among the near-ties standing the same way up, settling the tie when the
        # choice re-projects clearly better than every one; else the photos' edges may.
        candidates = [chosen, *rivals]
        checks = [check, *(check_of(alt) for alt in candidates[1:])]
        by_sight = _tiebreak(candidates, [seen_of(c) for c in candidates], model)
        by_boxes = _tiebreak(candidates, [c.mean_iou for c in checks], model)
        if by_sight.index == 0 and by_sight.margin >= RIVAL_SEEN_MARGIN:
            quality["settled_by_visibility"] = by_sight.to_json("visible_fitness")
            reasons = [r for r in reasons if not r.startswith(RUNNER_UP_REASON)]
        else:
            if by_boxes.index != 0 and not model.symmetry.is_symmetric:
                switched = candidates[by_boxes.index]
                quality.update(_fit_figures(model, scene, switched, pose.inlier_distance_m))
                # the pose step measured these of its own choice only
                quality.update(dict.fromkeys(CHOICE_FIGURES))
                quality["chosen_by"] = "reprojection"
                quality["switched_from_iou"] = round(check.mean_iou, 4)
                chosen, check = switched, checks[by_boxes.index]
            if by_boxes.margin >= RIVAL_IOU_MARGIN and chosen is candidates[by_boxes.index]:
                reasons = [r for r in reasons if not r.startswith(RUNNER_UP_REASON)]
                quality["settled_by_reprojection"] = by_boxes.to_json("mean_iou", "best_rival_iou")
    near_ties = [p for p in [pose.env_from_object, *rivals] if p is not chosen]
    moved = _on_photo_edges(model, chosen, sight, options)
    if moved is not None:
        chosen, reasons = _photo_step(
            model, moved, near_ties, sight, options, quality, reasons, pose.righted
        )
        quality.update(_fit_figures(model, scene, chosen, pose.inlier_distance_m))
        check = check_of(chosen)
    quality["visible_fitness"] = seen_of(chosen)
    reasons += check.rejections()
    quality.update(verified=not reasons, reasons=reasons, reprojection=check.to_json())
    centre = transform_points(chosen, model.centre_object[None, :])[0]
    return {"pose": chosen.tolist(), "pose_quality": quality, "centroid_env": centre.tolist()}


def _on_photo_edges(
    model: PreparedModel, env_from_object: Mat4, sight: CaptureSight, options: PoseOptions
) -> tuple[Mat4, dict[str, Any], tuple[str, ...], list[str]] | None:
    """The pose turned about the environment's up through the object's centre and shifted
    across the support onto the photos' edges
    (:func:`~workers.pipeline.pose.photo_edges.fit_photo_edges`), with its figures (photos
    used, mean pixels to the edges before and after, the turn, degrees modulo symmetry, and
    shift, metres, from ``env_from_object``); how the reasons the photos settle begin (the
    last fits' disagreement on the turn when the photos turned the pose by at most
    ``photo_edges_confirm_deg``: they confirm the last fit); and the reason it is not
    verified when that turn exceeds ``max_final_turn_deg`` (the scan and the photos
    disagree). A fit that lowers no cost keeps ``env_from_object``. None: no photo shows
    all of it (``photo_edges_max_views`` 0: never)."""
    fit = fit_photo_edges(
        model,
        env_from_object,
        UP_ENV,
        sight,
        options.photo_edges_cap_px,
        options.photo_edges_max_views,
    )
    if fit.views == 0:
        return None
    if not fit.cost < fit.start_cost:
        fit = replace(fit, env_from_object=env_from_object, cost=fit.start_cost)
    shift, turn = symmetric_pose_error(
        fit.env_from_object, env_from_object, model.symmetry, model.centre_object
    )
    figures = {
        "views": fit.views,
        "cost_px": round(fit.cost, 4),
        "start_cost_px": round(fit.start_cost, 4),
        "turn_deg": round(turn, 3),
        "shift_m": round(shift, 5),
    }
    settled = (FINAL_TURN_REASON,) if turn <= options.photo_edges_confirm_deg else ()
    limit = options.max_final_turn_deg
    turned = [f"the photos' edges turned the pose by {turn:.1f}° (> {limit:.1f}°)"]
    return fit.env_from_object, figures, settled, turned if turn > limit else []


_Moved = tuple[Mat4, dict[str, Any], tuple[str, ...], list[str]]


@dataclass(frozen=True)
class _PhotoTie:
    """The near-tie the photos' edges settle for: ``index`` into [the chosen pose, *the
    near-ties], its :func:`_on_photo_edges` result (``winner``) and the mean pixel costs of
    it and of the best other."""

    index: int
    winner: _Moved
    cost_px: float
    rival_px: float
    way_up_only: bool = False

    def to_json(self) -> dict[str, Any]:
        """``{"cost_px", "best_rival_px", "switched"}``, and ``"way_up_only": true`` when
        only the way up is settled."""
        out: dict[str, Any] = {
            "cost_px": round(self.cost_px, 4),
            "best_rival_px": round(self.rival_px, 4),
            "switched": self.index != 0,
        }
        if self.way_up_only:
            out["way_up_only"] = True
        return out


def _photo_step(
    model: PreparedModel,
    moved: _Moved,
    near_ties: Sequence[Mat4],
    sight: CaptureSight,
    options: PoseOptions,
    quality: dict[str, Any],
    reasons: list[str],
    righted: bool,
) -> tuple[Mat4, list[str]]:
    """The pose the photos' edges hold (``moved``, its figures put in ``quality``) and the
    reasons left: a near-tie they settle (:func:`_photo_tiebreak`; ``righted``: the pose
    step stood the pose upright against the scan) is dropped, for the near-tie they prefer
    if it is not the chosen pose (then the pose step's reasons all stand), else the last
    fits' disagreement they confirm; their turn beyond the limit is added."""
    chosen, quality["photo_edges"], settled, turned = moved
    tie = None
    if any(r.startswith(RUNNER_UP_REASON) for r in reasons):
        tie = _photo_tiebreak(model, moved, near_ties, sight, options, righted)
    if tie is not None:
        quality["settled_by_photo_edges"] = tie.to_json()
        if not tie.way_up_only:
            reasons = [r for r in reasons if not r.startswith(RUNNER_UP_REASON)]
        if tie.index != 0:  # the pose step's reasons stand: they were not about this pose
            chosen, quality["photo_edges"], _, turned = tie.winner
            settled = ()
            # the pose step measured these of its own choice only
            quality.update(dict.fromkeys(CHOICE_FIGURES))
            quality["chosen_by"] = "photo_edges"
    final_turn = quality.get("final_turn_deg")
    if not settled and not turned and final_turn and _disagree(reasons):
        back = _photo_basin_deg(model, chosen, float(final_turn), sight, options)
        quality["photo_edges"]["basin_deg"] = round(back, 3)
        settled = (FINAL_TURN_REASON,) if back <= PHOTO_BASIN_SHARE * final_turn else ()
    return chosen, [r for r in reasons if not r.startswith(settled)] + turned


def _disagree(reasons: Sequence[str]) -> bool:
    """Whether ``reasons`` hold the two last fits' disagreement."""
    return any(r.startswith(FINAL_TURN_REASON) for r in reasons)


def _photo_basin_deg(
    model: PreparedModel,
    env_from_object: Mat4,
    span_deg: float,
    sight: CaptureSight,
    o: PoseOptions,
) -> float:
    """How far (degrees, modulo symmetry) the photo fits from ``env_from_object`` turned
    by −``span_deg`` and by +``span_deg`` about the up through the object's centre (one
    start each) end from it, the larger; inf when a fit finds no photo. Small: the photos
    hold its turn over the span the scan leaves open."""
    centre = transform_points(env_from_object, model.centre_object[None, :])[0]
    worst = 0.0
    for turn_deg in (-span_deg, span_deg):
        x = np.array([np.radians(turn_deg), 0.0, 0.0])
        start = turned_in_plane(env_from_object, UP_ENV, centre, x)
        fit = fit_photo_edges(
            model, start, UP_ENV, sight, o.photo_edges_cap_px, o.photo_edges_max_views, (0.0,)
        )
        if fit.views == 0:
            return float("inf")
        turn = symmetric_pose_error(
            fit.env_from_object, env_from_object, model.symmetry, model.centre_object
        )[1]
        worst = max(worst, turn)
    return worst


def _photo_tiebreak(
    model: PreparedModel,
    moved: _Moved,
    near_ties: Sequence[Mat4],
    sight: CaptureSight,
    options: PoseOptions,
    righted: bool,
) -> _PhotoTie | None:
    """Each distinct near-tie fitted to the photos' edges as the chosen pose was
    (``moved``; the near-ties on ``options.threads`` threads): the one whose cost every
    other's exceeds :data:`RIVAL_PHOTO_RATIO` times. Else, when the pose step stood the
    chosen pose upright against the scan (``righted``), the best upside-down one when
    every upright one's cost exceeds it as many times: the photos settle the way up only
    (``way_up_only``), not the near-ties standing that way. None when neither, or when a
    near-tie has no photo that shows all of it."""
    others = ordered_map(
        lambda alt: _on_photo_edges(model, alt, sight, options), near_ties, options.threads
    )
    fits = [moved, *(f for f in others if f is not None)]
    if len(fits) < 1 + len(near_ties):  # a near-tie no photo shows all of
        return None
    costs = [float(f[1]["cost_px"]) for f in fits]
    best = int(np.argmin(costs))
    rival = min((c for i, c in enumerate(costs) if i != best), default=float("inf"))
    if rival >= RIVAL_PHOTO_RATIO * costs[best]:
        return _PhotoTie(best, fits[best], costs[best], rival)
    if not righted:
        return None
    up = [upright(f[0], model.up_object, UP_ENV) for f in fits]
    down = min((i for i in range(len(fits)) if not up[i]), key=costs.__getitem__, default=None)
    if down is None:
        return None
    standing = min((c for c, u in zip(costs, up, strict=True) if u), default=None)
    if standing is None or standing < RIVAL_PHOTO_RATIO * costs[down]:
        return None
    return _PhotoTie(down, fits[down], costs[down], standing, way_up_only=True)


@dataclass(frozen=True)
class _Tiebreak:
    """The near-tie a figure prefers: ``index`` into the candidates (0: the pose step's
    choice) of the best ``value`` among those standing the chosen pose's way up, and the
    best ``rival`` value of every other candidate."""

    index: int
    value: float
    rival: float

    @property
    def margin(self) -> float:
        """How much better the preferred candidate is than every other."""
        return self.value - self.rival

    def to_json(self, figure: str, rival: str = "best_rival") -> dict[str, float]:
        """``{figure: value, rival: rival value}``, rounded."""
        return {figure: round(self.value, 4), rival: round(self.rival, 4)}


def _tiebreak(
    candidates: Sequence[Mat4], values: Sequence[float | None], model: PreparedModel
) -> _Tiebreak:
    """:class:`_Tiebreak` of the 4×4 ``candidates`` (the chosen pose first) by ``values``
    (higher is better; None, not measured, ranks last)."""
    score = [-1.0 if v is None else float(v) for v in values]
    up = upright(candidates[0], model.up_object, UP_ENV)
    same_way = [i for i, c in enumerate(candidates) if upright(c, model.up_object, UP_ENV) == up]
    best = max(same_way, key=score.__getitem__)
    rival = max((v for i, v in enumerate(score) if i != best), default=0.0)
    return _Tiebreak(best, score[best], rival)


def _visible_fitness_of(
    model: PreparedModel,
    scene: SceneCloud,
    depth_maps: Sequence[DepthMap] | None,
    inlier_distance_m: float,
) -> Callable[[Mat4], float | None]:
    """:func:`~workers.pipeline.pose.verify.visible_fitness` of a pose of ``model`` (None
    without the capture's depth maps), computed once per pose (by identity)."""
    memo: dict[int, float | None] = {}

    def of(env_from_object: Mat4) -> float | None:
        if id(env_from_object) not in memo:
            memo[id(env_from_object)] = visible_fitness(
                model.points,
                model.normals,
                env_from_object,
                scene.points,
                depth_maps or (),
                inlier_distance_m,
            )
        return memo[id(env_from_object)]

    return of


def _fit_figures(
    model: PreparedModel, scene: SceneCloud, env_from_object: Any, inlier_distance_m: float
) -> dict[str, float]:
    """``fitness`` (share of model points within ``inlier_distance_m`` of the scene) and
    ``inlier_rmse`` (metres) of a pose, as the pose step reports them."""
    posed = transform_points(env_from_object, model.points)
    fitness, rmse = inlier_figures(scene_distances(posed, scene.points, inlier_distance_m))
    return {"fitness": fitness, "inlier_rmse": rmse}


def pose_changes(
    result: CompareResult,
    after: CaptureData,
    classes: Sequence[str],
    available: Collection[str],
    load_model: Callable[[str], PreparedModel],
    compare_options: CompareOptions,
    pose_options: Mapping[str, Any] | None = None,
    progress: Progress | None = None,
) -> list[dict[str, Any]]:
    """Every change of ``result`` as its contract JSON with ``centroid_env`` and, for added,
    moved and swapped objects whose class is in ``available``, ``pose`` (4×4
    env_from_object, metres) and ``pose_quality``. ``load_model(name)`` is called at most
    once per class, only for classes that need a pose. ``pose_options``: the job's
    ``{"preset": name, **overrides}`` for :class:`~workers.pipeline.pose.PoseOptions`
    (InputError for an unknown preset or option)."""
    report: Progress = progress or (lambda _stage, _fraction: None)
    options = pose_options_from_json(pose_options)
    posed = [c for c in result.changes if c.type in POSED_TYPES and c.object_name in available]
    scene = SceneCloud.create(after.points_env, colors=after.colors) if posed else None
    sight = CaptureSight(after, render_depth_maps(after, compare_options) if posed else None)
    prepared = {name: load_model(name) for name in dict.fromkeys(str(c.object_name) for c in posed)}

    def record(change: Change) -> dict[str, Any]:
        out = change.to_json()
        out["centroid_env"] = change.cluster.centroid.tolist()
        if change in posed and scene is not None:
            name = str(change.object_name)
            class_id = list(classes).index(name)
            out.update(pose_change(change, prepared[name], scene, sight, class_id, options))
        return out

    report("pose", 0.0)
    n = max(len(result.changes), 1)
    records = ordered_map(record, result.changes, options.threads, lambda k: report("pose", k / n))
    report("pose", 1.0)
    return records
