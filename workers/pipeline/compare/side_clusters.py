"""One side's clusters: DBSCAN → re-projection into the side's own capture → merging of
split clusters → hysteresis growth, skirt pruning and base growth → identification.

Indices are into the side's own cloud, points in the environment frame (metres), pixels in
the side's images. Merging is decided on the clusters as found (their sizes against the
class diameters), before growth.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from workers.pipeline.compare.clusters import (
    dbscan,
    groups_from_labels,
    grow_bases,
    grow_groups,
    merge_groups,
    prune_skirts,
    walls,
)
from workers.pipeline.compare.data import CaptureData
from workers.pipeline.compare.identify import (
    IdentificationTable,
    containment,
    identify,
    margins_px,
    yolo_to_boxes,
)
from workers.pipeline.compare.options import CompareOptions
from workers.pipeline.compare.results import ClusterResult, Side
from workers.pipeline.compare.visibility import DepthMap, box_from_pixels, visible_points

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
# pixels[image index] (n, 2): a cluster's visible pixels in each image where it is visible
ImagePixels = dict[int, FloatArray]
# boxes[image index] (4,): [x1, y1, x2, y2] pixels
ImageBoxes = dict[int, FloatArray]


@dataclass(frozen=True)
class SideInput:
    """One side's candidate points and what clustering them needs.

    ``candidates`` (n,) indices into ``capture``'s cloud above the threshold; ``low`` the
    points above the grow threshold (None: no growth); ``spacing_m`` the cloud's median
    point spacing; ``base_band_m`` the depth of base growth (0: off); ``depth_maps`` one
    z-buffer per camera (None: no occlusion test); ``first_id`` the id of its first cluster.
    """

    side: Side
    capture: CaptureData
    candidates: IntArray
    low: IntArray | None
    spacing_m: float
    base_band_m: float
    depth_maps: Sequence[DepthMap] | None
    first_id: int


@dataclass(frozen=True)
class Library:
    """``classes[i]`` is detector class id i; ``class_diameters_m`` the library objects'
    diameters; ``grow_max_m`` the reach of hysteresis growth, metres."""

    classes: Sequence[str]
    class_diameters_m: Mapping[str, float]
    grow_max_m: float


@dataclass(frozen=True)
class MergedClusters:
    """Clusters after merging (and growth): ``indices[c]`` into the cloud, ``partition[c]``
    the raw cluster numbers merged into c, ``n_seeds[c]`` its points before growth (None:
    not grown), ``pixels[c]`` its visible pixels per image."""

    indices: list[IntArray]
    partition: list[list[int]]
    n_seeds: list[int | None]
    pixels: list[ImagePixels]


def visible_pixels(
    capture: CaptureData,
    groups: Sequence[IntArray],
    depth_maps: Sequence[DepthMap] | None,
    options: CompareOptions,
) -> list[ImagePixels]:
    """``pixels[g][image]`` (n, 2): group g's visible pixels in each image where at least
    ``min_visible_points`` of its points are visible."""
    all_pts = capture.points_env[np.concatenate(groups)]
    # group g owns the points starts[g]:starts[g + 1] (owner ids are non-decreasing)
    owner = np.repeat(np.arange(len(groups)), [len(g) for g in groups])
    pixels: list[ImagePixels] = [{} for _ in groups]
    for ci, cam in enumerate(capture.cameras):
        dm = depth_maps[ci] if depth_maps is not None else None
        uv, vis = visible_points(
            cam, all_pts, dm, options.depth_tolerance_m, options.depth_tolerance_px
        )
        seen = np.flatnonzero(vis)
        bounds = np.searchsorted(owner[seen], np.arange(len(groups) + 1))
        for g in np.flatnonzero(np.diff(bounds) >= options.min_visible_points):
            pixels[g][ci] = uv[seen[bounds[g] : bounds[g + 1]]]
    return pixels


def _boxes(pixels: ImagePixels, percentile: float, min_area_px: float = 0.0) -> ImageBoxes:
    """Each image's box of the pixels, where its area is at least ``min_area_px``."""
    boxes = {i: box_from_pixels(p, percentile) for i, p in pixels.items()}
    return {i: b for i, b in boxes.items() if (b[2] - b[0]) * (b[3] - b[1]) >= min_area_px}


def _detections(capture: CaptureData) -> list[tuple[FloatArray, IntArray]]:
    """Per camera: the detector's (M, 4) pixel boxes and (M,) class ids."""
    return [
        yolo_to_boxes(capture.detections.get(cam.name, np.zeros((0, 6))), cam.width, cam.height)
        for cam in capture.cameras
    ]


def _merge_partition(
    groups: Sequence[IntArray],
    pixels: Sequence[ImagePixels],
    dets: Sequence[tuple[FloatArray, IntArray]],
    capture: CaptureData,
    library: Library,
    options: CompareOptions,
) -> list[list[int]]:
    """Which raw clusters form one object: each cluster is assigned, per image, the
    detection containing ≥ ``merge_containment`` of its box; see clusters.merge_groups."""
    classes = library.classes
    assigned: list[dict[int, tuple[int, str]]] = []
    for group_pixels in pixels:
        amap: dict[int, tuple[int, str]] = {}
        for img, box in _boxes(group_pixels, options.box_percentile).items():
            det, cls = dets[img]
            if len(det) == 0:
                continue
            frac = containment(box[None, :], det)[0]
            j = int(np.argmax(frac))
            if frac[j] >= options.merge_containment and 0 <= cls[j] < len(classes):
                amap[img] = (j, classes[int(cls[j])])
        assigned.append(amap)
    return merge_groups(
        groups,
        capture.points_env,
        assigned,
        library.class_diameters_m,
        options.merge_shared_fraction,
        options.merge_size_margin,
    )


def _grow(
    seeds: list[IntArray],
    side: SideInput,
    low: IntArray,
    grow_max_m: float,
    options: CompareOptions,
) -> list[IntArray]:
    """Hysteresis growth through ``low`` points, then skirt pruning and base growth (each
    when on)."""
    points = side.capture.points_env
    spacing = side.spacing_m
    radius = options.cluster_radius_factor * spacing
    grown = grow_groups(seeds, points, low, radius, grow_max_m)
    if options.skirt_width_factor > 0:
        grown = prune_skirts(
            grown,
            seeds,
            points,
            options.skirt_radius_factor * spacing,
            options.skirt_rise_m,
            options.skirt_width_factor * spacing,
        )
    if side.base_band_m > 0:
        radius_xy = options.base_radius_factor * spacing
        anchors = None
        if options.base_beneath_walls:
            wall_radius = options.skirt_radius_factor * spacing
            anchors = walls(grown, points, wall_radius, options.skirt_rise_m)
        grown = grow_bases(grown, points, radius_xy, side.base_band_m, anchors=anchors)
    return grown


def _merged_pixels(partition: list[list[int]], pixels: Sequence[ImagePixels]) -> list[ImagePixels]:
    """The pixels of each merged cluster: its parts' pixels, per image."""
    merged: list[ImagePixels] = []
    for part in partition:
        images = sorted({i for g in part for i in pixels[g]})
        merged.append(
            {
                img: np.concatenate([pixels[g][img] for g in part if img in pixels[g]])
                for img in images
            }
        )
    return merged


def _merge_and_grow(
    groups: list[IntArray],
    side: SideInput,
    dets: Sequence[tuple[FloatArray, IntArray]],
    library: Library,
    options: CompareOptions,
) -> MergedClusters:
    """Merge split clusters, then grow them when ``side.low`` is given."""
    pixels = visible_pixels(side.capture, groups, side.depth_maps, options)
    partition: list[list[int]] = [[g] for g in range(len(groups))]
    if options.merge_clusters and len(groups) > 1:
        partition = _merge_partition(groups, pixels, dets, side.capture, library, options)
    merged = [np.concatenate([groups[g] for g in part]) for part in partition]
    if side.low is None:
        n_none: list[int | None] = [None] * len(merged)
        return MergedClusters(merged, partition, n_none, _merged_pixels(partition, pixels))
    n_seeds: list[int | None] = [len(m) for m in merged]
    grown = _grow(merged, side, side.low, library.grow_max_m, options)
    grown_pixels = visible_pixels(side.capture, grown, side.depth_maps, options)
    return MergedClusters(grown, partition, n_seeds, grown_pixels)


def _cluster_results(
    side: SideInput,
    merged: MergedClusters,
    boxes: Sequence[ImageBoxes],
    table: IdentificationTable,
    classes: Sequence[str],
    options: CompareOptions,
) -> list[ClusterResult]:
    """One ClusterResult per merged cluster, named by the identification table."""
    cams = side.capture.cameras
    out: list[ClusterResult] = []
    rows = zip(merged.indices, boxes, merged.partition, merged.n_seeds, strict=True)
    for c, (idx, image_boxes, part, n_seed) in enumerate(rows):
        best = table.best(c, options.identify_threshold)
        out.append(
            ClusterResult(
                id=side.first_id + c,
                side=side.side,
                indices=idx,
                points_env=side.capture.points_env[idx],
                boxes={cams[i].name: b for i, b in image_boxes.items()},
                occurrences=int(table.occurrences[c]),
                overlaps={k: int(table.overlaps[c, j]) for j, k in enumerate(classes)},
                mean_iou={k: float(table.mean_iou[c, j]) for j, k in enumerate(classes)},
                metrics={k: float(table.metric[c, j]) for j, k in enumerate(classes)},
                object_name=None if best is None else classes[best],
                merged_from=tuple(part),
                n_seed_points=n_seed,
            )
        )
    return out


def side_clusters(
    side: SideInput, library: Library, options: CompareOptions
) -> list[ClusterResult]:
    """Cluster, re-project, merge, grow and identify one side's candidate points."""
    pts = side.capture.points_env[side.candidates]
    radius = options.cluster_radius_factor * side.spacing_m
    labels = dbscan(pts, radius, options.cluster_min_samples, options.cluster_min_points)
    groups = [side.candidates[g] for g in groups_from_labels(labels, options.max_clusters)]
    if not groups:
        return []
    dets = _detections(side.capture)
    merged = _merge_and_grow(groups, side, dets, library, options)
    boxes = [_boxes(p, options.box_percentile, options.min_box_area_px) for p in merged.pixels]
    margins = margins_px(side.capture.cameras, options.box_margin)
    table = identify(boxes, dets, library.classes, margins)
    return _cluster_results(side, merged, boxes, table, library.classes, options)
