"""The pose step after a comparison: a 6-DoF pose for every identified object that appeared,
each checked by re-projection into the after capture's detections.

Shared by the comparison job (workers/comparison.py) and the benchmarks, so both pose the
same way. Pure: prepared models come in through ``load_model``; nothing is read from
storage here.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Mapping, Sequence
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from workers.pipeline.compare.data import Camera, CaptureData
from workers.pipeline.compare.options import CompareOptions
from workers.pipeline.compare.results import Change, CompareResult
from workers.pipeline.compare.stage import render_depth_maps
from workers.pipeline.compare.visibility import DepthMap
from workers.pipeline.errors import PipelineError
from workers.pipeline.geometry import Mat4, transform_points
from workers.pipeline.model import PreparedModel
from workers.pipeline.pose.candidates import distinct_pose, upright
from workers.pipeline.pose.crop import SceneCloud
from workers.pipeline.pose.estimate import estimate_pose
from workers.pipeline.pose.options import PoseOptions, pose_options_from_json
from workers.pipeline.pose.result import CHOICE_FIGURES, PoseResult
from workers.pipeline.pose.verify import RUNNER_UP_REASON, ReprojectionCheck, reprojection_check

POSED_TYPES = frozenset({"added", "moved", "swapped"})
#: how much better (mean IoU with the detector's boxes) the chosen pose must re-project than
#: any distinct near-tie before the tie counts as settled
RIVAL_IOU_MARGIN = 0.1
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
    after: CaptureData,
    class_id: int,
    depth_maps: Sequence[DepthMap] | None,
    options: PoseOptions,
) -> dict[str, Any]:
    """Pose, quality and centre of one change; a failed registration is reported on the
    change (``verified: false`` with the reason), never dropped."""
    try:
        pose = estimate_pose(
            model,
            scene,
            cluster_points_env=change.cluster.points_env,
            previous_env_from_object=change.previous_env_from_object,
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

    chosen = pose.env_from_object
    check = check_of(chosen)
    quality = pose.quality_json()
    quality["chosen_by"] = pose.chosen_by
    reasons = list(pose.rejections)
    if any(r.startswith(RUNNER_UP_REASON) for r in reasons):
        # A distinct pose fits the cloud almost as well (a near-symmetric object, such as a
        # bracket turned end for end): the detector's boxes choose among the near-ties that
        # stand the same way up (a box cannot tell an object from itself upside down; the
        # pose step chose that), and settle the tie when the choice explains the boxes
        # clearly better than every near-tie.
        up = upright(chosen, model.up_object, UP_ENV)
        checked = [
            (check, chosen),
            *((check_of(alt), alt) for alt in _rivals(pose, model, options)),
        ]
        best_check, best_pose = max(
            (pair for pair in checked if upright(pair[1], model.up_object, UP_ENV) == up),
            key=lambda pair: pair[0].mean_iou,
        )
        second_iou = max((c.mean_iou for c, p in checked if p is not best_pose), default=0.0)
        if best_pose is not chosen and not model.symmetry.is_symmetric:
            quality.update(_fit_figures(model, scene, best_pose, pose.inlier_distance_m))
            # the pose step measured these of its own choice only
            quality.update(dict.fromkeys(CHOICE_FIGURES))
            quality["chosen_by"] = "reprojection"
            quality["switched_from_iou"] = round(check.mean_iou, 4)
            chosen, check = best_pose, best_check
        if check.mean_iou >= second_iou + RIVAL_IOU_MARGIN:
            reasons = [r for r in reasons if not r.startswith(RUNNER_UP_REASON)]
            quality["settled_by_reprojection"] = {
                "mean_iou": round(check.mean_iou, 4),
                "best_rival_iou": round(second_iou, 4),
            }
    if not check.passed:
        reasons.append(
            f"re-projection: mean IoU {check.mean_iou:.2f} over {check.views} views "
            "with the detector's boxes is too low"
        )
    quality.update(verified=not reasons, reasons=reasons, reprojection=check.to_json())
    centre = transform_points(chosen, model.centre_object[None, :])[0]
    return {
        "pose": chosen.tolist(),
        "pose_quality": quality,
        "centroid_env": centre.tolist(),
    }


def _fit_figures(
    model: PreparedModel, scene: SceneCloud, env_from_object: Any, inlier_distance_m: float
) -> dict[str, float]:
    """``fitness`` (share of model points within ``inlier_distance_m`` of the scene) and
    ``inlier_rmse`` (metres) of a pose, as the pose step reports them."""
    posed = transform_points(env_from_object, model.points)
    lo, hi = posed.min(axis=0) - inlier_distance_m, posed.max(axis=0) + inlier_distance_m
    near = scene.points[np.all((scene.points >= lo) & (scene.points <= hi), axis=1)]
    if len(near) == 0:
        return {"fitness": 0.0, "inlier_rmse": 0.0}
    d, _ = cKDTree(near).query(posed, distance_upper_bound=inlier_distance_m)
    inliers = d[np.isfinite(d)]
    rmse = float(np.sqrt(np.mean(inliers**2))) if len(inliers) else 0.0
    return {"fitness": float(len(inliers) / len(posed)), "inlier_rmse": rmse}


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
    depth_maps = render_depth_maps(after, compare_options) if posed else None
    prepared: dict[str, PreparedModel] = {}
    records: list[dict[str, Any]] = []
    for i, change in enumerate(result.changes):
        report("pose", i / max(len(result.changes), 1))
        record = change.to_json()
        record["centroid_env"] = change.cluster.centroid.tolist()
        if change in posed and scene is not None:
            name = str(change.object_name)
            if name not in prepared:
                prepared[name] = load_model(name)
            record.update(
                pose_change(
                    change,
                    prepared[name],
                    scene,
                    after,
                    list(classes).index(name),
                    depth_maps,
                    options,
                )
            )
        records.append(record)
    report("pose", 1.0)
    return records
