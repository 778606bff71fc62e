"""Identification metric (thesis eq. 3.1) against hand-computed values."""

from __future__ import annotations

import numpy as np
import pytest

from workers.pipeline.compare.identify import (
    containment,
    identify,
    iou_matrix,
    margins_px,
    yolo_to_boxes,
)
from workers.pipeline.errors import ComparisonError


def test_iou_and_containment() -> None:
    a = np.array([[0.0, 0.0, 10.0, 10.0]])
    b = np.array([[0.0, 0.0, 10.0, 5.0], [5.0, 0.0, 15.0, 10.0], [20.0, 20.0, 30.0, 30.0]])
    np.testing.assert_allclose(iou_matrix(a, b), [[0.5, 1 / 3, 0.0]])
    np.testing.assert_allclose(containment(a, b), [[0.5, 0.5, 0.0]])
    np.testing.assert_allclose(iou_matrix(a, np.array([[3.0, 3.0, 3.0, 3.0]])), [[0.0]])


def test_yolo_to_pixel_boxes() -> None:
    boxes, cls = yolo_to_boxes(np.array([[2, 0.5, 0.25, 0.1, 0.5, 0.9]]), 200, 100)
    np.testing.assert_allclose(boxes, [[90.0, 0.0, 110.0, 50.0]])
    assert cls.tolist() == [2]


def test_metric_equals_hand_computed_value() -> None:
    # cluster visible in 3 images (occurrences = 3)
    box = np.array([0.0, 0.0, 10.0, 10.0])
    cluster_boxes = [{0: box, 1: box, 2: box + 100}]
    dets = [
        # image 0: two class-0 boxes, IoU 0.5 and 1.0 → best 1.0
        (np.array([[0.0, 0.0, 10.0, 5.0], [0.0, 0.0, 10.0, 10.0]]), np.array([0, 0])),
        # image 1: class 0 IoU 1/3, class 1 IoU 1.0
        (np.array([[5.0, 0.0, 15.0, 10.0], [0.0, 0.0, 10.0, 10.0]]), np.array([0, 1])),
        # image 2: a class-0 box elsewhere (IoU 0: no overlap)
        (np.array([[0.0, 0.0, 10.0, 10.0]]), np.array([0])),
    ]
    t = identify(cluster_boxes, dets, ["a", "b", "c"])
    assert t.occurrences.tolist() == [3]
    assert t.overlaps.tolist() == [[2, 1, 0]]
    # class a: mean IoU (1 + 1/3)/2 = 2/3, × overlaps/occurrences 2/3 → 4/9
    np.testing.assert_allclose(t.mean_iou[0], [2 / 3, 1.0, 0.0])
    np.testing.assert_allclose(t.metric[0], [4 / 9, 1 / 3, 0.0])
    assert t.best(0, 0.4) == 0
    assert t.best(0, 0.5) is None


def test_cluster_never_visible_scores_zero_and_bad_class_raises() -> None:
    t = identify([{}], [(np.zeros((0, 4)), np.zeros(0, dtype=np.int64))], ["a"])
    assert t.occurrences.tolist() == [0] and t.metric.tolist() == [[0.0]]
    with pytest.raises(ComparisonError):
        identify(
            [{0: np.array([0.0, 0, 1, 1])}], [(np.array([[0.0, 0, 1, 1]]), np.array([3]))], ["a"]
        )


def _noisy_metric(size_px: tuple[float, float], margin_px: float, gap_px: float = 0.0) -> float:
    """Metric over 40 images of a box of ``size_px`` whose cluster box and detection box
    each carry σ 2 px edge noise (the detection ``gap_px`` to the right when given)."""
    rng = np.random.default_rng(0)
    w, h = size_px
    truth = np.array([100.0, 100.0, 100.0 + w, 100.0 + h])
    cluster, dets = {}, []
    for i in range(40):
        cluster[i] = truth + rng.normal(0, 2.0, 4)
        det = truth + rng.normal(0, 2.0, 4) + np.array([1, 0, 1, 0]) * (w + gap_px) * (gap_px > 0)
        dets.append((det[None, :], np.array([0])))
    margins = np.full(40, margin_px)
    return float(identify([cluster], dets, ["a"], margins).metric[0, 0])


def test_a_margin_lifts_a_small_objects_iou_from_the_detectors_noise() -> None:
    """A padlock-sized box (14 × 9 px) scores far below a large one from σ 2 px edge noise
    alone; a 4 px margin lifts it past 0.5 and moves the large one little, and a box 12 px
    beside another still does not overlap it."""
    small, large = (14.0, 9.0), (200.0, 150.0)
    assert _noisy_metric(small, 0.0) < 0.5
    assert _noisy_metric(small, 4.0) > _noisy_metric(small, 0.0) + 0.1
    assert _noisy_metric(small, 4.0) > 0.5
    assert abs(_noisy_metric(large, 4.0) - _noisy_metric(large, 0.0)) < 0.03
    assert _noisy_metric(small, 4.0, gap_px=12.0) < 0.05
    cams = [
        type("C", (), {"width": 800, "height": 600})(),
        type("C", (), {"width": 600, "height": 960})(),
    ]
    np.testing.assert_allclose(margins_px(cams, 0.005), [4.0, 4.8])
