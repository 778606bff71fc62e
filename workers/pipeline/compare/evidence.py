"""Evidence for a cluster beyond its own capture: what the other capture's detector saw at
its place, and the twin instance it lies on.

- *Still there*: an identified cluster's points projected into the **other** capture's
  images and scored against that capture's detections (the same table as identify.py).
  A removed object that the after capture's detector still boxes as its class at its
  place was not removed: the after reconstruction lost its surface (a hole). Likewise an
  added object boxed in the before images was there already.
- *Part of a standing object*: a cluster whose box lies inside a detection of one class
  (``merge_containment``) in at least ``merge_shared_fraction`` of its views in **both**
  captures is a piece of an object that stood there before and after, reconstructed
  differently (surface texture, light), not a change, whatever name it got (a piece on a
  twin instance scores that class too).
- *Named by the twin*: a removed cluster the detector does not name on its own, lying on
  a twin instance, takes that instance's class when the class still scores a lower
  threshold: the twin says what stood there, the detector agrees in part (a small or flat
  object's cluster is too loose a box to reach the identification threshold).
- *Named at a removal's place*: an added cluster the detector does not name, standing
  where an identified object was removed, takes its best other class at the same lower
  threshold (a swap in place: the new object's cluster holds the floor the old one
  covered, a looser box); one cluster per removal, the best scoring.
- *The other end of a move*: an identified cluster whose class has no identified cluster
  on the other side is one end of a move or a plain addition/removal; the unidentified
  cluster of the other side that scores best for that class, at the same lower
  threshold, away from the end's own place (a swap's reach) but within
  ``moved_max_distance``, is named that class when the capture it is missing from scores
  the class there below that threshold (the object was not there then; a flat object's
  new place is too loose a box to be named on its own).

Points in the environment frame (metres), pixels in the scored capture's images.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from workers.pipeline.compare.data import CaptureData, TwinInstance
from workers.pipeline.compare.identify import (
    IdentificationTable,
    containment,
    identify,
    margins_px,
    yolo_to_boxes,
)
from workers.pipeline.compare.options import CompareOptions
from workers.pipeline.compare.results import ClusterResult
from workers.pipeline.compare.visibility import DepthMap, box_from_pixels, visible_points

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Captures:
    """Both captures, the z-buffers their visibility tests use (None: no occlusion test)
    and the detector's classes (class id i is ``classes[i]``)."""

    before: CaptureData
    after: CaptureData
    maps_before: Sequence[DepthMap] | None
    maps_after: Sequence[DepthMap] | None
    classes: Sequence[str]

    def other(self, cluster: ClusterResult) -> tuple[CaptureData, Sequence[DepthMap] | None]:
        """The capture ``cluster`` is not from, and its z-buffers."""
        if cluster.side == "removed":
            return self.after, self.maps_after
        return self.before, self.maps_before


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


def points_table(
    point_sets: Sequence[FloatArray],
    capture: CaptureData,
    depth_maps: Sequence[DepthMap] | None,
    classes: Sequence[str],
    options: CompareOptions,
) -> IdentificationTable:
    """The identification table of each (N, 3) point set (environment frame, metres) against
    ``capture``'s images and detections (visibility against its z-buffers ``depth_maps``)."""
    dets = [
        yolo_to_boxes(capture.detections.get(cam.name, np.zeros((0, 6))), cam.width, cam.height)
        for cam in capture.cameras
    ]
    boxes = [occurrence_boxes(p, capture, depth_maps, options) for p in point_sets]
    return identify(boxes, dets, classes, margins_px(capture.cameras, options.box_margin))


def cross_capture_table(
    clusters: Sequence[ClusterResult],
    other: CaptureData,
    other_maps: Sequence[DepthMap] | None,
    classes: Sequence[str],
    options: CompareOptions,
) -> IdentificationTable:
    """The identification table of ``clusters``' points against the **other** capture's
    images and detections (visibility against its z-buffers ``other_maps``)."""
    return points_table([c.points_env for c in clusters], other, other_maps, classes, options)


def still_there(
    clusters: Sequence[ClusterResult], captures: Captures, options: CompareOptions
) -> set[int]:
    """Ids of identified clusters whose class the other capture's detector names at their
    place with a metric ≥ ``still_there_metric`` (removed: the after capture; added: the
    before one). Empty when the option is None."""
    if options.still_there_metric is None:
        return set()
    out: set[int] = set()
    for side in ("removed", "added"):
        named = [c for c in clusters if c.side == side and c.object_name is not None]
        if not named:
            continue
        other, maps = captures.other(named[0])
        table = cross_capture_table(named, other, maps, captures.classes, options)
        for row, c in enumerate(named):
            k = list(captures.classes).index(str(c.object_name))
            if table.metric[row, k] >= options.still_there_metric:
                out.add(c.id)
    return out


def contained_shares(
    points_env: FloatArray,
    capture: CaptureData,
    depth_maps: Sequence[DepthMap] | None,
    classes: Sequence[str],
    options: CompareOptions,
) -> FloatArray:
    """(K,) share per class of the views of ``capture`` where the points occur
    (:func:`occurrence_boxes`) in which a detection of that class contains at least
    ``merge_containment`` of their box (zeros where they occur nowhere)."""
    boxes = occurrence_boxes(points_env, capture, depth_maps, options)
    held = np.zeros(len(classes))
    for img, box in boxes.items():
        cam = capture.cameras[img]
        det, cls = yolo_to_boxes(
            capture.detections.get(cam.name, np.zeros((0, 6))), cam.width, cam.height
        )
        if len(det) == 0:
            continue
        inside = containment(box[None, :], det)[0] >= options.merge_containment
        for k in set(cls[inside].tolist()):
            if 0 <= k < len(classes):
                held[k] += 1
    return held / max(len(boxes), 1)


def parts_of_standing_objects(
    clusters: Sequence[ClusterResult], captures: Captures, options: CompareOptions
) -> set[int]:
    """Ids of clusters inside detections of one class in at least
    ``merge_shared_fraction`` of their views in both captures (:func:`contained_shares`):
    parts of an object standing in both. Empty when ``still_there_metric`` is None."""
    if options.still_there_metric is None:
        return set()
    out: set[int] = set()
    for c in clusters:
        shares = [
            contained_shares(c.points_env, capture, maps, captures.classes, options)
            for capture, maps in (
                (captures.before, captures.maps_before),
                (captures.after, captures.maps_after),
            )
        ]
        if np.any(np.minimum(*shares) >= options.merge_shared_fraction):
            out.add(c.id)
    return out


def join_split_objects(
    clusters: Sequence[ClusterResult],
    class_diameters_m: Mapping[str, float],
    options: CompareOptions,
    skip: Collection[int] = (),
) -> tuple[list[ClusterResult], set[int]]:
    """Identified clusters of one class on one side that together fit within one object
    (their points' extent at most ``merge_size_margin`` × its diameter) are one object
    split in parts: the best identified one takes the others' points, and their ids are
    returned as parts (no change of their own). Clusters whose ids are in ``skip`` (parts
    of standing objects) take no part. Two objects of one class touching are joined too
    (their extent fits one only when they are small against it)."""
    out = list(clusters)
    parts: set[int] = set()
    order = sorted(
        (i for i, c in enumerate(out) if c.object_name in class_diameters_m and c.id not in skip),
        key=lambda i: -out[i].metrics.get(str(out[i].object_name), 0.0),
    )
    for i in order:
        if out[i].id in parts:
            continue
        head = out[i]
        limit = options.merge_size_margin * class_diameters_m[str(head.object_name)]
        for j in order:
            other = out[j]
            if j == i or other.id in parts or other.side != head.side:
                continue
            if other.object_name != head.object_name:
                continue
            joined = np.vstack([head.points_env, other.points_env])
            if float(np.max(np.ptp(joined, axis=0))) > limit:
                continue
            head = dataclasses.replace(
                head,
                indices=np.concatenate([head.indices, other.indices]),
                points_env=joined,
                merged_from=head.merged_from + other.merged_from,
            )
            parts.add(other.id)
        out[i] = head
    return out, parts


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


def _other_capture_metric(
    cluster: ClusterResult, name: str, captures: Captures, options: CompareOptions
) -> float:
    """Metric of class ``name`` for ``cluster``'s points in the capture it is not from."""
    other, maps = captures.other(cluster)
    table = cross_capture_table([cluster], other, maps, captures.classes, options)
    return float(table.metric[0, list(captures.classes).index(name)])


def name_move_ends(
    clusters: Sequence[ClusterResult],
    class_diameters_m: Mapping[str, float],
    captures: Captures,
    options: CompareOptions,
    pieces: Collection[int] = (),
) -> list[ClusterResult]:
    """``clusters`` with, for each identified cluster whose class no identified cluster of
    the other side has (best metric first), the other side's unidentified cluster scoring
    best for that class named by it, when that metric is at least
    ``twin_identify_threshold``, the two lie between ``swap_distance_factor`` × the class
    diameter (not the end's own place: the floor a removed object covered, say) and
    ``moved_max_distance`` apart, and the capture the candidate is missing from scores the
    class at its place below that threshold
    (unchanged when ``twin_identify_threshold`` is None). Clusters in ``pieces`` (ids of
    :func:`parts_of_standing_objects`: another standing instance of the class) are no
    candidates."""
    low = options.twin_identify_threshold
    if low is None:
        return list(clusters)
    out = list(clusters)
    ends = sorted(
        (c for c in out if c.object_name is not None),
        key=lambda c: -c.metrics.get(str(c.object_name), 0.0),
    )
    for end in ends:
        name = str(end.object_name)
        if any(c.side != end.side and c.object_name == name for c in out):
            continue
        near = options.swap_distance_factor * float(class_diameters_m.get(name, 0.0))
        candidates = [
            i
            for i, c in enumerate(out)
            if c.side != end.side
            and c.object_name is None
            and c.id not in pieces
            and c.metrics.get(name, 0.0) >= low
            and near
            <= float(np.linalg.norm(c.centroid - end.centroid))
            <= options.moved_max_distance
        ]
        for i in sorted(candidates, key=lambda i: -out[i].metrics.get(name, 0.0)):
            there = _other_capture_metric(out[i], name, captures, options)
            if there < low:
                out[i] = dataclasses.replace(out[i], object_name=name)
                break
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
