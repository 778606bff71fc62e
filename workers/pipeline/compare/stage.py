"""The compare stage: two snapshots in the environment frame → clusters, identities, changes.

Steps: C2C both ways → thresholds → candidate points → "not seen ≠ removed" filter →
DBSCAN per side → re-projection with visibility into the side's own capture → merging of
split clusters → hysteresis growth through points above the lower threshold, less the
smeared floor around each foot (skirt pruning), then the band beneath its walls (base
growth) →
identification table (thesis eq. 3.1) → change types against the twin.
Pure: no files, no database; randomness (z-buffer point subsets, spacing samples) is seeded.
"""

from __future__ import annotations

import dataclasses
import time
import uuid
from collections.abc import Callable, Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from workers.pipeline.compare.c2c import c2c_both_ways
from workers.pipeline.compare.changes import classify_changes
from workers.pipeline.compare.clusters import (
    dbscan,
    groups_from_labels,
    grow_bases,
    grow_groups,
    merge_groups,
    prune_skirts,
    walls,
)
from workers.pipeline.compare.data import CaptureData, TwinInstance
from workers.pipeline.compare.identify import containment, identify, yolo_to_boxes
from workers.pipeline.compare.options import PRESETS, CompareOptions
from workers.pipeline.compare.results import ClusterResult, CompareResult, Side
from workers.pipeline.compare.thresholds import (
    CloudStats,
    DistanceStats,
    cloud_stats,
    distance_stats,
)
from workers.pipeline.compare.visibility import (
    DepthMap,
    box_from_pixels,
    covered_mask,
    render_depth,
    seen_empty_counts,
    visible_points,
)
from workers.pipeline.errors import ComparisonError, InputError

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
Progress = Callable[[str, float], None]


def render_depth_maps(capture: CaptureData, options: CompareOptions) -> list[DepthMap]:
    """One z-buffer per camera of ``capture`` from (a seeded subset of) its own cloud."""
    pts = capture.points_env
    if len(pts) > options.zbuffer_max_points:
        rng = np.random.default_rng(options.seed)
        pts = pts[rng.choice(len(pts), options.zbuffer_max_points, replace=False)]
    pts32 = np.ascontiguousarray(pts.T, dtype=np.float32)  # (3, N) columns
    return [
        render_depth(cam, pts32, options.zbuffer_max_side, options.zbuffer_fill_px)
        for cam in capture.cameras
    ]


def _sample_indices(n: int, size: int, seed: int) -> IntArray:
    """All of range(n), or a sorted seeded sample of ``size`` of them."""
    if n <= size:
        return np.arange(n, dtype=np.int64)
    rng = np.random.default_rng(seed)
    return np.sort(rng.choice(n, size=size, replace=False)).astype(np.int64)


def _check_inputs(classes: Sequence[str], class_diameters_m: Mapping[str, float]) -> None:
    if len(set(classes)) != len(classes) or not all(isinstance(c, str) and c for c in classes):
        raise InputError("classes must be unique non-empty names")
    for name, d in class_diameters_m.items():
        if not (np.isfinite(d) and d > 0):
            raise InputError(f"diameter of {name!r} must be finite and > 0, got {d}")


def _visible_pixels(
    capture: CaptureData,
    groups: Sequence[IntArray],
    depth_maps: Sequence[DepthMap] | None,
    options: CompareOptions,
) -> list[dict[int, FloatArray]]:
    """``pixels[g][image]`` (n, 2): group g's visible pixels in each image where at least
    ``min_visible_points`` of its points are visible."""
    all_pts = capture.points_env[np.concatenate(groups)]
    # group g owns the points starts[g]:starts[g + 1] (owner ids are non-decreasing)
    owner = np.repeat(np.arange(len(groups)), [len(g) for g in groups])
    pixels: list[dict[int, FloatArray]] = [{} for _ in groups]
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


def _side_clusters(
    side: Side,
    capture: CaptureData,
    candidates: IntArray,
    low: IntArray | None,
    grow_max_m: float,
    base_band_m: float,
    spacing_m: float,
    depth_maps: Sequence[DepthMap] | None,
    classes: Sequence[str],
    class_diameters_m: Mapping[str, float],
    options: CompareOptions,
    first_id: int,
) -> list[ClusterResult]:
    """Cluster, re-project, merge, grow (through ``low`` points, when given, then down
    ``base_band_m`` beneath, when > 0) and identify one side's candidate points (indices
    into the capture's cloud). Merging is decided on the clusters as found (their sizes
    against the class diameters), before growth."""
    pts = capture.points_env[candidates]
    radius = options.cluster_radius_factor * spacing_m
    labels = dbscan(pts, radius, options.cluster_min_samples, options.cluster_min_points)
    groups = [candidates[g] for g in groups_from_labels(labels, options.max_clusters)]
    if not groups:
        return []
    cams = capture.cameras
    pixels = _visible_pixels(capture, groups, depth_maps, options)
    dets = [
        yolo_to_boxes(capture.detections.get(cam.name, np.zeros((0, 6))), cam.width, cam.height)
        for cam in cams
    ]

    def boxes_of(pix: dict[int, FloatArray]) -> dict[int, FloatArray]:
        return {i: box_from_pixels(p, options.box_percentile) for i, p in pix.items()}

    partition: list[list[int]] = [[g] for g in range(len(groups))]
    if options.merge_clusters and len(groups) > 1:
        assigned: list[dict[int, tuple[int, str]]] = []
        for group_pixels in pixels:
            amap: dict[int, tuple[int, str]] = {}
            for img, box in boxes_of(group_pixels).items():
                det, cls = dets[img]
                if len(det) == 0:
                    continue
                frac = containment(box[None, :], det)[0]
                j = int(np.argmax(frac))
                if frac[j] >= options.merge_containment and 0 <= cls[j] < len(classes):
                    amap[img] = (j, classes[int(cls[j])])
            assigned.append(amap)
        partition = merge_groups(
            groups,
            capture.points_env,
            assigned,
            class_diameters_m,
            options.merge_shared_fraction,
            options.merge_size_margin,
        )
    merged_idx = [np.concatenate([groups[g] for g in part]) for part in partition]
    n_seeds: list[int | None] = [None] * len(merged_idx)
    if low is not None:
        n_seeds = [len(m) for m in merged_idx]
        seed_idx = merged_idx
        merged_idx = grow_groups(merged_idx, capture.points_env, low, radius, grow_max_m)
        if options.skirt_width_factor > 0:
            merged_idx = prune_skirts(
                merged_idx,
                seed_idx,
                capture.points_env,
                options.skirt_radius_factor * spacing_m,
                options.skirt_rise_m,
                options.skirt_width_factor * spacing_m,
            )
        if base_band_m > 0:
            radius_xy = options.base_radius_factor * spacing_m
            anchors = None
            if options.base_beneath_walls:
                wall_radius = options.skirt_radius_factor * spacing_m
                anchors = walls(merged_idx, capture.points_env, wall_radius, options.skirt_rise_m)
            merged_idx = grow_bases(
                merged_idx, capture.points_env, radius_xy, base_band_m, anchors=anchors
            )
        merged_pixels = _visible_pixels(capture, merged_idx, depth_maps, options)
    else:
        merged_pixels = []
        for part in partition:
            images = sorted({i for g in part for i in pixels[g]})
            merged_pixels.append(
                {
                    img: np.concatenate([pixels[g][img] for g in part if img in pixels[g]])
                    for img in images
                }
            )
    merged_boxes = [boxes_of(p) for p in merged_pixels]
    table = identify(merged_boxes, dets, classes)
    out: list[ClusterResult] = []
    rows = zip(merged_idx, merged_boxes, partition, n_seeds, strict=True)
    for c, (idx, boxes, part, n_seed) in enumerate(rows):
        best = table.best(c, options.identify_threshold)
        out.append(
            ClusterResult(
                id=first_id + c,
                side=side,
                indices=idx,
                points_env=capture.points_env[idx],
                boxes={cams[i].name: b for i, b in boxes.items()},
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


def compare_snapshots(
    before: CaptureData,
    after: CaptureData,
    twin: Sequence[TwinInstance],
    classes: Sequence[str],
    class_diameters_m: Mapping[str, float],
    options: CompareOptions = PRESETS["default"],
    progress: Progress | None = None,
    *,
    new_id: Callable[[], str] | None = None,
) -> CompareResult:
    """Compare two snapshots (both in the environment frame, metres) against the twin.

    ``classes[i]`` is detector class id i; ``class_diameters_m`` the library objects'
    diameters (used to merge split clusters and to decide "same place" for swaps);
    ``progress(stage, fraction)`` is called along the way and may raise Cancelled;
    ``new_id`` makes new instance/change ids (default: UUID4).
    Raises ShapeError/InputError for bad inputs, ComparisonError when a cloud is unusable.
    """
    report: Progress = progress or (lambda _stage, _fraction: None)
    make_id: Callable[[], str] = new_id or (lambda: str(uuid.uuid4()))
    _check_inputs(classes, class_diameters_m)
    # wall-clock seconds per step, and the process's CPU seconds (all threads): on a
    # shared machine the wall clock measures the load, the CPU time the work
    timings: dict[str, float] = {}
    cpu: dict[str, float] = {}
    t_wall, t_cpu = time.perf_counter(), time.process_time()

    def lap(name: str) -> None:
        nonlocal t_wall, t_cpu
        now_wall, now_cpu = time.perf_counter(), time.process_time()
        timings[name] = round(now_wall - t_wall, 4)
        cpu[name] = round(now_cpu - t_cpu, 4)
        t_wall, t_cpu = now_wall, now_cpu

    report("compare.distances", 0.0)
    c2c = c2c_both_ways(before.points_env, after.points_env)
    lap("c2c")
    grow = options.grow_threshold
    specs = [options.threshold] + ([grow] if grow is not None else [])
    nb = max(spec.neighbours for spec in specs)
    lod = any(spec.kind == "lod" for spec in specs)
    stats_b = cloud_stats(c2c.tree_before, options.spacing_sample, nb, options.seed, lod)
    stats_a = cloud_stats(c2c.tree_after, options.spacing_sample, nb, options.seed, lod)
    lap("cloud_stats")

    report("compare.visibility", 0.2)
    overlap = options.stats_region == "overlap"
    need_after = options.use_visibility or options.check_seen_removed or overlap
    need_before = options.use_visibility or options.check_seen_added or overlap
    maps_after = render_depth_maps(after, options) if need_after else None
    maps_before = render_depth_maps(before, options) if need_before else None
    lap("zbuffers")

    reg = float(np.hypot(before.alignment_residual_m, after.alignment_residual_m))
    tol = (options.depth_tolerance_m, options.depth_tolerance_px)

    def side_stats(
        dist: FloatArray,
        own: CaptureData,
        other_maps: list[DepthMap] | None,
        compared: CloudStats,
        reference: CloudStats,
    ) -> DistanceStats:
        region, sample = "all", dist
        if overlap and other_maps:
            idx = _sample_indices(len(dist), options.stats_sample, options.seed)
            covered = covered_mask(own.points_env[idx], other_maps, *tol)
            if np.count_nonzero(covered) >= options.cluster_min_points:
                region, sample = "overlap", dist[idx[covered]]
        out = distance_stats(sample, options.threshold, compared, reference, reg, region)
        if grow is None:
            return out
        low = distance_stats(sample, grow, compared, reference, reg, region).threshold
        return dataclasses.replace(out, grow_threshold=min(low, out.threshold))

    dist_added = side_stats(c2c.added, after, maps_before, stats_a, stats_b)
    dist_removed = side_stats(c2c.removed, before, maps_after, stats_b, stats_a)
    cand_added = np.flatnonzero(c2c.added > dist_added.threshold).astype(np.int64)
    cand_removed = np.flatnonzero(c2c.removed > dist_removed.threshold).astype(np.int64)
    n_cand = {"added": int(cand_added.size), "removed": int(cand_removed.size)}
    # growth candidates: above the lower threshold (grow_groups keeps those within reach)
    reach_m = options.grow_max_diameters * max(class_diameters_m.values(), default=0.0)
    low_added = low_removed = None
    if dist_added.grow_threshold is not None and dist_removed.grow_threshold is not None:
        low_added = np.flatnonzero(c2c.added > dist_added.grow_threshold)
        low_removed = np.flatnonzero(c2c.removed > dist_removed.grow_threshold)
    lap("thresholds")

    if options.check_seen_removed and maps_after is not None:
        seen = seen_empty_counts(before.points_env[cand_removed], maps_after, *tol)
        cand_removed = cand_removed[seen >= options.min_seen_views]
    # growth points need no such evidence: the seeds decide which clusters exist, growth
    # only completes them within its reach. A removed object's base lies within the depth
    # tolerance of the floor seen behind it, so it can never be seen as empty (measured: a
    # removed can's box lacked its lowest 6–19 px in all 35 views when growth was filtered)
    lap("seen_check")

    report("compare.clusters", 0.5)
    vis_after = maps_after if options.use_visibility else None
    vis_before = maps_before if options.use_visibility else None
    clusters = _side_clusters(
        "added",
        after,
        cand_added,
        low_added,
        reach_m,
        options.base_band_factor * (dist_added.grow_threshold or 0.0),
        stats_a.spacing,
        vis_after,
        classes,
        class_diameters_m,
        options,
        1,
    )
    clusters += _side_clusters(
        "removed",
        before,
        cand_removed,
        low_removed,
        reach_m,
        options.base_band_factor * (dist_removed.grow_threshold or 0.0),
        stats_b.spacing,
        vis_before,
        classes,
        class_diameters_m,
        options,
        len(clusters) + 1,
    )
    lap("clusters_identify")

    report("compare.changes", 0.9)
    # Added points where the old capture saw empty space. Only unidentified clusters need
    # this evidence (a hole in the old cloud is not an addition); an identified object can
    # stand where the old capture could not look, e.g. inside a swapped object's volume.
    # Judged on the cluster's points above the strict threshold (grown points lie close
    # to old surfaces by construction).
    unevidenced: set[int] = set()
    if options.check_seen_added and maps_before is not None:
        unknown = [c for c in clusters if c.side == "added" and c.object_name is None]
        strict = [c.indices[c2c.added[c.indices] > dist_added.threshold] for c in unknown]
        if unknown:  # one pass over the cameras for all of them
            seen = seen_empty_counts(after.points_env[np.concatenate(strict)], maps_before, *tol)
            owner = np.repeat(np.arange(len(unknown)), [len(idx) for idx in strict])
            n_seen = np.bincount(owner[seen >= options.min_seen_views], minlength=len(unknown))
            for c, idx, k in zip(unknown, strict, n_seen, strict=True):
                if k < options.min_seen_fraction * len(idx):
                    unevidenced.add(c.id)
    try:
        changes = classify_changes(
            clusters, twin, class_diameters_m, options, make_id, not_changes=unevidenced
        )
    except ValueError as exc:  # linear_sum_assignment on degenerate input
        raise ComparisonError(f"could not pair changes: {exc}") from exc
    lap("changes")
    report("compare.changes", 1.0)
    stats = {
        "points": {"before": len(before.points_env), "after": len(after.points_env)},
        "spacing_m": {"before": stats_b.spacing, "after": stats_a.spacing},
        "roughness_m": {"before": stats_b.roughness, "after": stats_a.roughness} if lod else None,
        "candidates": n_cand,
        "candidates_seen": {"added": int(cand_added.size), "removed": int(cand_removed.size)},
        "timings_s": timings,
        "cpu_s": cpu,
    }
    return CompareResult(
        options=options,
        distances={"added": dist_added, "removed": dist_removed},
        clusters=tuple(clusters),
        changes=tuple(changes),
        added_distances_m=c2c.added,
        removed_distances_m=c2c.removed,
        stats=stats,
    )
