"""Re-projection check of an estimated pose against the detector's boxes.

The thesis had no way to check a pose. Here the posed model is projected into every image of
the capture that saw it, keeping the model points the capture's own depth says are visible,
and the box of those pixels is compared with the detector's boxes of the object's class: a
right pose lands on the detections (IoU near 1), a wrong one does not.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from workers.pipeline.compare.data import Camera, FloatArray
from workers.pipeline.compare.identify import iou_matrix, yolo_to_boxes
from workers.pipeline.compare.visibility import DepthMap, box_from_pixels, visible_points
from workers.pipeline.geometry import as_mat4, as_points, transform_points


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

    def to_json(self) -> dict[str, Any]:
        return {
            "mean_iou": round(self.mean_iou, 4),
            "views": self.views,
            "visible_views": self.visible_views,
            "passed": self.passed,
        }


def reprojection_check(
    model_points_object: FloatArray,
    env_from_object: FloatArray,
    class_id: int,
    cameras: Sequence[Camera],
    detections: Mapping[str, FloatArray],
    depth_maps: Sequence[DepthMap] | None = None,
    *,
    min_iou: float = 0.5,
    min_views: int = 2,
    min_pixels: int = 20,
    tol_m: float = 0.02,
) -> ReprojectionCheck:
    """Project (N, 3) model points (object frame, metres) posed by the 4×4 ``env_from_object``
    into ``cameras`` (optionally occlusion-tested against the capture's ``depth_maps``, one
    per camera) and score their boxes against the YOLO rows of ``class_id``."""
    points_env = transform_points(
        as_mat4(env_from_object, "env_from_object"), as_points(model_points_object)
    )
    if depth_maps is not None and len(depth_maps) != len(cameras):
        raise ValueError("depth_maps must have one map per camera")
    ious: list[float] = []
    visible_views = 0
    for i, camera in enumerate(cameras):
        depth = depth_maps[i] if depth_maps is not None else None
        uv, visible = visible_points(camera, points_env, depth, tol_m=tol_m)
        if int(visible.sum()) < min_pixels:
            continue
        visible_views += 1
        rows = detections.get(camera.name)
        if rows is None or len(rows) == 0:
            continue
        boxes, ids = yolo_to_boxes(np.asarray(rows, dtype=np.float64), camera.width, camera.height)
        boxes = boxes[ids == class_id]
        if len(boxes) == 0:
            continue
        model_box = box_from_pixels(uv[visible], percentile=1.0)[None, :]
        ious.append(float(iou_matrix(model_box, boxes).max()))
    mean_iou = float(np.mean(ious)) if ious else 0.0
    return ReprojectionCheck(
        mean_iou=mean_iou,
        views=len(ious),
        visible_views=visible_views,
        passed=len(ious) >= min_views and mean_iou >= min_iou,
    )
