"""Step 4 of pose estimation: verification of a pose, in 3D and against the detector's boxes.

In 3D (:func:`verify_fit`): ``fitness`` (share of model points with a scene point within the
inlier distance), the share of cluster points explained by the posed model, the score of the
best *distinct* alternative and how well the scan holds the rotation; ``verified`` needs all
of them within the :class:`~workers.pipeline.pose.options.PoseOptions` thresholds. The inlier
RMSE is reported, not judged: bounded by the inlier distance, it measures the cloud's noise
against the object's voxel, not the pose.

Against what the cameras saw (:func:`visible_fitness`): the share of the posed model's
surface in the cameras' view that the scan holds; a pose turned over or beside the object
puts surface where the cameras saw none.

By re-projection (:func:`reprojection_check`): the posed model is projected into every image of
the capture that saw it, keeping the model points the capture's own depth says are visible,
and the box of those pixels is compared with the detector's boxes of the object's class: a
right pose lands on the detections (IoU near 1), a wrong one does not.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import ConvexHull, QhullError, cKDTree

from workers.pipeline.compare.data import Camera, FloatArray
from workers.pipeline.compare.identify import iou_matrix, yolo_to_boxes
from workers.pipeline.compare.visibility import (
    DepthMap,
    box_from_pixels,
    seen_by_any,
    visible_points,
)
from workers.pipeline.geometry import Mat4, Points, as_mat4, as_points, transform_points
from workers.pipeline.pose.options import PoseOptions
from workers.pipeline.pose.refine import Refinement

#: the rejection a near-tie in 3D gets; the caller may settle it with 2D evidence
RUNNER_UP_REASON = "a distinct pose scores"
#: how the reason that the pose step's last fits disagree on the turn begins
FINAL_TURN_REASON = "the last fit turned the ICP pose by"


@dataclass(frozen=True)
class FitVerification:
    """The 3D verification of one pose: ``cluster_coverage`` (None without cluster points)
    and the ``rejections`` (empty: verified)."""

    cluster_coverage: float | None
    rejections: tuple[str, ...]

    @property
    def verified(self) -> bool:
        """True when nothing rejects the pose."""
        return not self.rejections


def cluster_coverage(
    cluster: Points, model_points: Points, env_from_object: Mat4, v: float, o: PoseOptions
) -> float:
    """Share of (K, 3) cluster points (environment frame) the model posed by 4×4
    ``env_from_object`` explains: within a noise-scaled tolerance of its (N, 3) points
    (object frame), or inside their convex hull. The tolerance is 3σ of the cluster's own
    scatter about the model (σ = 1.4826 × the median distance), clipped to
    ``coverage_voxels·v`` … ``max_coverage_voxels·v`` and ``max_inlier_distance_m`` — a
    reconstructed cloud scatters 2-4 mm about the true surface, and a cluster that includes
    something else leaves it uncovered by centimetres. Inside the hull lie stereo's points
    across a hollow object's opening and in a flat one's gaps, not another object."""
    posed = transform_points(env_from_object, model_points)
    hi = min(o.max_coverage_voxels * v, o.max_inlier_distance_m)
    d, _ = cKDTree(posed).query(cluster, distance_upper_bound=hi)
    d_med = float(np.median(np.where(np.isfinite(d), d, hi)))
    tol = float(np.clip(3.0 * 1.4826 * d_med, min(o.coverage_voxels * v, hi), hi))
    covered = d <= tol
    if not covered.all():
        local = transform_points(np.linalg.inv(env_from_object), cluster[~covered])
        covered[~covered] = inside_hull(model_points, local)
    return float(np.mean(covered))


def inside_hull(hull_points: Points, points: Points) -> NDArray[np.bool_]:
    """(K,) whether each of the (K, 3) ``points`` lies inside the convex hull of the
    (N, 3) ``hull_points`` (same frame); all False when those span no volume."""
    try:
        planes = ConvexHull(hull_points).equations
    except QhullError:
        return np.zeros(len(points), dtype=bool)
    inside: NDArray[np.bool_] = np.all(points @ planes[:, :3].T + planes[:, 3] <= 0.0, axis=1)
    return inside


def verify_fit(
    fit: Refinement, model_points: Points, cluster: Points | None, v: float, o: PoseOptions
) -> FitVerification:
    """Step 4: reject the refined pose when ``fitness < min_fitness`` (or no model point has
    a scan point within the inlier distance), a distinct pose scores above
    ``max_runner_up_ratio`` × the best (two poses that explain the data about equally
    well are not a verified pose), or the cluster coverage is below
    ``min_cluster_coverage``, or the scan's residual level hides a turn of more than
    ``max_rotation_slack_deg`` or the last fit turned the refinement's ICP pose by more than
    ``max_final_turn_deg`` (the scan does not settle its rotation), or it had to be set
    down on its support from a tilt beyond the rest window. ``model_points``:
    (N, 3) object frame; ``cluster``: (K, 3) environment frame or None."""
    coverage: float | None = None
    if cluster is not None:
        coverage = cluster_coverage(cluster, model_points, fit.env_from_object, v, o)
    fitness = fit.fitness
    rejections: list[str] = []
    if fitness < o.min_fitness or fitness == 0.0:
        rejections.append(f"fitness {fitness:.2f} < {o.min_fitness:.2f}")
    if fit.runner_up > o.max_runner_up_ratio * fit.score:
        ratio = fit.runner_up / fit.score
        rejections.append(f"{RUNNER_UP_REASON} {ratio:.2f} of the best (> {o.max_runner_up_ratio})")
    if fit.rotation_slack_deg > o.max_rotation_slack_deg:
        rejections.append(
            f"the scan's residuals hide a turn of {fit.rotation_slack_deg:.1f}° "
            f"(> {o.max_rotation_slack_deg:.1f}°)"
        )
    if fit.final_turn_deg > o.max_final_turn_deg:
        rejections.append(
            f"{FINAL_TURN_REASON} {fit.final_turn_deg:.1f}° (> {o.max_final_turn_deg:.1f}°)"
        )
    if fit.tipped_deg > 0.0:
        rejections.append(
            f"it touched its support on nothing it could rest on: set down, turned by "
            f"{fit.tipped_deg:.1f}° (> rest_max_tilt_deg {o.rest_max_tilt_deg:g}°)"
        )
    if coverage is not None and coverage < o.min_cluster_coverage:
        rejections.append(f"cluster coverage {coverage:.2f} < {o.min_cluster_coverage:.2f}")
    return FitVerification(coverage, tuple(rejections))


#: fewer model points than this in view of the cameras: no visible fitness
MIN_VISIBLE_POINTS = 50


def scene_distances(points: Points, scene_points: Points, reach_m: float) -> FloatArray:
    """(N,) distance (metres) from each of the (N, 3) points to the nearest of the (M, 3)
    ``scene_points``; inf beyond ``reach_m`` (only the scene within the points' box grown
    by ``reach_m`` is searched)."""
    lo, hi = points.min(axis=0) - reach_m, points.max(axis=0) + reach_m
    near = scene_points[np.all((scene_points >= lo) & (scene_points <= hi), axis=1)]
    if len(near) == 0:
        return np.full(len(points), np.inf)
    tree = cKDTree(near, balanced_tree=False, compact_nodes=False)  # built fast, same distances
    d, _ = tree.query(points, distance_upper_bound=reach_m)
    return np.asarray(d, dtype=np.float64)


def visible_fitness(
    model_points: Points,
    model_normals: Points,
    env_from_object: Mat4,
    scene_points: Points,
    depth_maps: Sequence[DepthMap],
    inlier_distance_m: float,
) -> float | None:
    """Share of the posed (N, 3) model points (object frame, unit outward ``model_normals``)
    that the cameras see (facing one, in its image, not hidden behind the capture's own
    depth, :func:`~workers.pipeline.compare.visibility.seen_by_any`) with a (M, 3)
    ``scene_points`` point within ``inlier_distance_m``: what the cameras should have
    reconstructed of the object, if it stood there. A pose turned over or beside the
    object puts surface where the scan has none. None with fewer than
    :data:`MIN_VISIBLE_POINTS` such points (no cameras, or the object out of view)."""
    rot = env_from_object[:3, :3]
    posed = transform_points(env_from_object, model_points)
    seen = seen_by_any(posed, model_normals @ rot.T, depth_maps)
    if int(seen.sum()) < MIN_VISIBLE_POINTS:
        return None
    d = scene_distances(posed[seen], scene_points, inlier_distance_m)
    return float(np.mean(np.isfinite(d)))


@dataclass(frozen=True)
class ReprojectionOptions:
    """Thresholds of the re-projection check: ``min_iou`` mean IoU over at least
    ``min_views`` views; a view counts when ≥ ``min_pixels`` model points are visible in it,
    a point being visible within ``tol_m`` metres of the capture's depth."""

    min_iou: float = 0.5
    min_views: int = 2
    min_pixels: int = 20
    tol_m: float = 0.02


@dataclass(frozen=True)
class ReprojectionCheck:
    """``mean_iou`` over the views where the posed model is visible (≥ ``min_pixels``
    projected points) and the class was detected; ``views`` how many such views;
    ``visible_views`` views where the model is visible at all; ``passed`` whether
    ``mean_iou`` ≥ the threshold over ≥ ``min_views`` views."""

    mean_iou: float
    views: int
    visible_views: int
    passed: bool

    def rejections(self) -> list[str]:
        """Why the pose fails the check (empty when it passed)."""
        if self.passed:
            return []
        return [
            f"re-projection: mean IoU {self.mean_iou:.2f} over {self.views} views "
            "with the detector's boxes is too low"
        ]

    def to_json(self) -> dict[str, Any]:
        return {
            "mean_iou": round(self.mean_iou, 4),
            "views": self.views,
            "visible_views": self.visible_views,
            "passed": self.passed,
        }


def _view_iou(
    camera: Camera, detections: FloatArray | None, class_id: int, uv_visible: FloatArray
) -> float | None:
    """Best IoU of the box of the visible projected model pixels (P, 2) with the YOLO rows
    of ``class_id`` in one view; None when the class was not detected there."""
    if detections is None or len(detections) == 0:
        return None
    boxes, ids = yolo_to_boxes(
        np.asarray(detections, dtype=np.float64), camera.width, camera.height
    )
    boxes = boxes[ids == class_id]
    if len(boxes) == 0:
        return None
    model_box = box_from_pixels(uv_visible, percentile=1.0)[None, :]
    return float(iou_matrix(model_box, boxes).max())


def reprojection_check(
    model_points_object: FloatArray,
    env_from_object: FloatArray,
    class_id: int,
    cameras: Sequence[Camera],
    detections: Mapping[str, FloatArray],
    depth_maps: Sequence[DepthMap] | None = None,
    options: ReprojectionOptions = ReprojectionOptions(),
) -> ReprojectionCheck:
    """Project (N, 3) model points (object frame, metres) posed by the 4×4 ``env_from_object``
    into ``cameras`` (optionally occlusion-tested against the capture's ``depth_maps``, one
    per camera) and score their boxes against the YOLO rows of ``class_id``. ValueError when
    ``depth_maps`` is not one map per camera."""
    points_env = transform_points(
        as_mat4(env_from_object, "env_from_object"), as_points(model_points_object)
    )
    if depth_maps is not None and len(depth_maps) != len(cameras):
        raise ValueError("depth_maps must have one map per camera")
    ious: list[float] = []
    visible_views = 0
    for i, camera in enumerate(cameras):
        depth = depth_maps[i] if depth_maps is not None else None
        uv, visible = visible_points(camera, points_env, depth, tol_m=options.tol_m)
        if int(visible.sum()) < options.min_pixels:
            continue
        visible_views += 1
        iou = _view_iou(camera, detections.get(camera.name), class_id, uv[visible])
        if iou is not None:
            ious.append(iou)
    mean_iou = float(np.mean(ious)) if ious else 0.0
    return ReprojectionCheck(
        mean_iou=mean_iou,
        views=len(ious),
        visible_views=visible_views,
        passed=len(ious) >= options.min_views and mean_iou >= options.min_iou,
    )
