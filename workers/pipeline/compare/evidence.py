"""Evidence for a cluster beyond its own capture: what the other capture's detector saw at
its place, and the twin instance it lies on.

- *Still there*: an identified cluster's points projected into the **other** capture's
  images and scored against that capture's detections (the same table as identify.py).
  A removed object that the after capture's detector still boxes as its class at its
  place was not removed: the after reconstruction lost its surface (a hole). Likewise an
  added object boxed in the before images was there already.
- *Named by the twin*: a removed cluster the detector does not name on its own, lying on
  a twin instance, takes that instance's class when the class still scores a lower
  threshold: the twin says what stood there, the detector agrees in part (a small or flat
  object's cluster is too loose a box to reach the identification threshold).
- *Named at a removal's place*: an added cluster the detector does not name, standing
  where an identified object was removed, takes its best other class at the same lower
  threshold (a swap in place: the new object's cluster holds the floor the old one
  covered, a looser box); one cluster per removal, the best scoring.

Points in the environment frame (metres), pixels in the scored capture's images.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from workers.pipeline.compare.data import CaptureData, TwinInstance
from workers.pipeline.compare.identify import IdentificationTable, identify, yolo_to_boxes
from workers.pipeline.compare.options import CompareOptions
from workers.pipeline.compare.results import ClusterResult
from workers.pipeline.compare.visibility import DepthMap, box_from_pixels, visible_points

FloatArray = NDArray[np.float64]


def occurrence_boxes(
    points_env: FloatArray,
    capture: CaptureData,
    depth_maps: Sequence[DepthMap] | None,
    options: CompareOptions,
) -> dict[int, FloatArray]:
    """Image index → (4,) box px of (N, 3) points in each of ``capture``'s images where at
    least ``min_visible_points`` of them are visible and the box has at least
    ``min_box_area_px`` pixels (where the detector could box them)."""
    out: dict[int, FloatArray] = {}
    for ci, cam in enumerate(capture.cameras):
        dm = depth_maps[ci] if depth_maps is not None else None
        uv, vis = visible_points(
            cam, points_env, dm, options.depth_tolerance_m, options.depth_tolerance_px
        )
        if np.count_nonzero(vis) < options.min_visible_points:
            continue
        box = box_from_pixels(uv[vis], options.box_percentile)
        if (box[2] - box[0]) * (box[3] - box[1]) >= options.min_box_area_px:
            out[ci] = box
    return out


def cross_capture_table(
    clusters: Sequence[ClusterResult],
    other: CaptureData,
    other_maps: Sequence[DepthMap] | None,
    classes: Sequence[str],
    options: CompareOptions,
) -> IdentificationTable:
    """The identification table of ``clusters``' points against the **other** capture's
    images and detections (visibility against its z-buffers ``other_maps``)."""
    dets = [
        yolo_to_boxes(other.detections.get(cam.name, np.zeros((0, 6))), cam.width, cam.height)
        for cam in other.cameras
    ]
    boxes = [occurrence_boxes(c.points_env, other, other_maps, options) for c in clusters]
    return identify(boxes, dets, classes)


def still_there(
    clusters: Sequence[ClusterResult],
    before: CaptureData,
    after: CaptureData,
    maps_before: Sequence[DepthMap] | None,
    maps_after: Sequence[DepthMap] | None,
    classes: Sequence[str],
    options: CompareOptions,
) -> set[int]:
    """Ids of identified clusters whose class the other capture's detector names at their
    place with a metric ≥ ``still_there_metric`` (removed: the after capture; added: the
    before one). Empty when the option is None."""
    if options.still_there_metric is None:
        return set()
    out: set[int] = set()
    for side, other, maps in (("removed", after, maps_after), ("added", before, maps_before)):
        named = [c for c in clusters if c.side == side and c.object_name is not None]
        if not named:
            continue
        table = cross_capture_table(named, other, maps, classes, options)
        for row, c in enumerate(named):
            k = classes.index(str(c.object_name))
            if table.metric[row, k] >= options.still_there_metric:
                out.add(c.id)
    return out


def _instance_at(
    cluster: ClusterResult,
    twin: Sequence[TwinInstance],
    class_diameters_m: Mapping[str, float],
    options: CompareOptions,
) -> TwinInstance | None:
    """The nearest twin instance whose centroid lies within its match reach
    (``max(instance_match_min, instance_match_factor × diameter)``) of the cluster's."""
    best: tuple[float, TwinInstance] | None = None
    for inst in twin:
        reach = max(
            options.instance_match_min,
            options.instance_match_factor * float(class_diameters_m.get(inst.object_name, 0.0)),
        )
        d = float(np.linalg.norm(cluster.centroid - inst.centroid))
        if d <= reach and (best is None or d < best[0]):
            best = (d, inst)
    return None if best is None else best[1]


def name_by_twin(
    clusters: Sequence[ClusterResult],
    twin: Sequence[TwinInstance],
    class_diameters_m: Mapping[str, float],
    options: CompareOptions,
) -> list[ClusterResult]:
    """``clusters`` with each unidentified removed cluster that lies on a twin instance
    named by that instance's class when its metric for the class is at least
    ``twin_identify_threshold`` (unchanged when the option is None)."""
    low = options.twin_identify_threshold
    if low is None or not twin:
        return list(clusters)
    out = []
    for c in clusters:
        if c.side == "removed" and c.object_name is None:
            inst = _instance_at(c, twin, class_diameters_m, options)
            if inst is not None and c.metrics.get(inst.object_name, 0.0) >= low:
                c = dataclasses.replace(c, object_name=inst.object_name)
        out.append(c)
    return out


def _best_other(c: ClusterResult, not_class: str) -> tuple[str, float]:
    """The cluster's best-scoring class other than ``not_class`` and its metric."""
    others = [(k, v) for k, v in c.metrics.items() if k != not_class]
    return max(others, key=lambda kv: kv[1], default=("", 0.0))


def name_at_removals(
    clusters: Sequence[ClusterResult],
    class_diameters_m: Mapping[str, float],
    options: CompareOptions,
) -> list[ClusterResult]:
    """``clusters`` with, for each identified removed cluster, the best unidentified added
    cluster within ``swap_distance_factor × max(diameters)`` of it named by its best other
    class when that scores at least ``twin_identify_threshold`` (unchanged when None)."""
    low = options.twin_identify_threshold
    if low is None:
        return list(clusters)
    out = list(clusters)
    for r in [c for c in clusters if c.side == "removed" and c.object_name is not None]:
        best: tuple[float, int, str] | None = None
        for i, c in enumerate(out):
            if c.side != "added" or c.object_name is not None:
                continue
            name, metric = _best_other(c, str(r.object_name))
            reach = options.swap_distance_factor * max(
                float(class_diameters_m.get(str(r.object_name), 0.0)),
                float(class_diameters_m.get(name, 0.0)),
            )
            near = float(np.linalg.norm(c.centroid - r.centroid)) < reach
            if near and metric >= low and (best is None or metric > best[0]):
                best = (metric, i, name)
        if best is not None:
            out[best[1]] = dataclasses.replace(out[best[1]], object_name=best[2])
    return out
