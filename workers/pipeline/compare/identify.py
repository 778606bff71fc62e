"""Identification of clusters by IoU with the detector's boxes (thesis equation 3.1).

For a cluster c and a class k over the images of the cluster's capture:
``occurrences`` = images where c is visible (has a box); ``overlaps_k`` = those images where
a class-k detection box overlaps c's box (IoU > 0); ``mean_iou_k`` = the mean, over those
overlapping images, of the best IoU with a class-k box; and
``metric_k = mean_iou_k × overlaps_k / occurrences`` (= Σ best IoU / occurrences).

Both boxes may be padded by a margin per image before their IoU (the detector's box noise:
a few pixels that would otherwise cap a small object's IoU far below a large one's).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from workers.pipeline.errors import ComparisonError

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


def yolo_to_boxes(rows: FloatArray, width: int, height: int) -> tuple[FloatArray, IntArray]:
    """(M, 4) pixel boxes ``[x1, y1, x2, y2]`` and (M,) class ids of (M, ≥5) YOLO rows."""
    if len(rows) == 0:
        return np.zeros((0, 4)), np.zeros(0, dtype=np.int64)
    cx, cy = rows[:, 1] * width, rows[:, 2] * height
    hw, hh = rows[:, 3] * width / 2, rows[:, 4] * height / 2
    boxes = np.column_stack([cx - hw, cy - hh, cx + hw, cy + hh])
    return boxes, np.rint(rows[:, 0]).astype(np.int64)


def margins_px(cameras: Sequence[Any], fraction: float) -> FloatArray:
    """(I,) box margin of each camera's image: ``fraction`` of its longer side, pixels."""
    return np.asarray([fraction * max(c.width, c.height) for c in cameras], dtype=np.float64)


def _padded(boxes: FloatArray, margin_px: float) -> FloatArray:
    """(M, 4) boxes ``[x1, y1, x2, y2]`` grown by ``margin_px`` on every side."""
    return np.asarray(boxes + np.array([-margin_px, -margin_px, margin_px, margin_px]), np.float64)


def _intersection(a: FloatArray, b: FloatArray) -> FloatArray:
    w = np.clip(
        np.minimum(a[:, None, 2], b[None, :, 2]) - np.maximum(a[:, None, 0], b[None, :, 0]), 0, None
    )
    h = np.clip(
        np.minimum(a[:, None, 3], b[None, :, 3]) - np.maximum(a[:, None, 1], b[None, :, 1]), 0, None
    )
    return np.asarray(w * h, dtype=np.float64)


def _area(a: FloatArray) -> FloatArray:
    return np.asarray(np.clip(a[:, 2] - a[:, 0], 0, None) * np.clip(a[:, 3] - a[:, 1], 0, None))


def iou_matrix(a: FloatArray, b: FloatArray) -> FloatArray:
    """IoU (P, Q) between (P, 4) and (Q, 4) boxes ``[x1, y1, x2, y2]``; 0 for empty boxes."""
    inter = _intersection(a, b)
    union = _area(a)[:, None] + _area(b)[None, :] - inter
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(union > 0, inter / union, 0.0)


def containment(a: FloatArray, b: FloatArray) -> FloatArray:
    """Fraction (P, Q) of each box of ``a`` (P, 4) that lies inside each box of ``b`` (Q, 4)."""
    inter = _intersection(a, b)
    area = _area(a)[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(area > 0, inter / area, 0.0)


@dataclass(frozen=True, eq=False)
class IdentificationTable:
    """Cluster × class table: ``occurrences`` (C,), ``overlaps`` (C, K), ``mean_iou`` (C, K),
    ``metric`` (C, K)."""

    classes: tuple[str, ...]
    occurrences: IntArray
    overlaps: IntArray
    mean_iou: FloatArray
    metric: FloatArray

    def best(self, cluster: int, threshold: float) -> int | None:
        """Index of the identified class of ``cluster`` (highest metric ≥ threshold) or None."""
        if self.metric.shape[1] == 0:
            return None
        k = int(np.argmax(self.metric[cluster]))
        return k if self.metric[cluster, k] >= threshold and self.metric[cluster, k] > 0 else None


def identify(
    cluster_boxes: Sequence[Mapping[int, FloatArray]],
    detection_boxes: Sequence[tuple[FloatArray, IntArray]],
    classes: Sequence[str],
    margins: FloatArray | None = None,
) -> IdentificationTable:
    """The full identification table.

    ``cluster_boxes[c]`` maps an image index to cluster c's (4,) box in that image (only
    images where it is visible); ``detection_boxes[i]`` is image i's ((M, 4) boxes, (M,)
    class ids); ``margins[i]`` image i's box margin, pixels (None: none). Raises
    ComparisonError for a class id outside ``classes``.
    """
    n_c, n_k = len(cluster_boxes), len(classes)
    occ = np.zeros(n_c, dtype=np.int64)
    ovl = np.zeros((n_c, n_k), dtype=np.int64)
    iou_sum = np.zeros((n_c, n_k))
    pads = np.zeros(len(detection_boxes)) if margins is None else margins
    padded = [_padded(det, float(pad)) for (det, _), pad in zip(detection_boxes, pads, strict=True)]
    for ci, boxes in enumerate(cluster_boxes):
        for img, box in boxes.items():
            occ[ci] += 1
            det, cls = detection_boxes[img]
            if len(det) == 0:
                continue
            if cls.min() < 0 or cls.max() >= n_k:
                raise ComparisonError(
                    f"detection class id out of range 0..{n_k - 1} in image {img}"
                )
            ious = iou_matrix(_padded(box[None, :], float(pads[img])), padded[img])[0]
            best = np.zeros(n_k)
            np.maximum.at(best, cls, ious)
            hit = best > 0
            ovl[ci, hit] += 1
            iou_sum[ci, hit] += best[hit]
    with np.errstate(divide="ignore", invalid="ignore"):
        mean_iou = np.where(ovl > 0, iou_sum / np.maximum(ovl, 1), 0.0)
        metric = np.where(occ[:, None] > 0, mean_iou * ovl / np.maximum(occ[:, None], 1), 0.0)
    return IdentificationTable(tuple(classes), occ, ovl, mean_iou, metric)
