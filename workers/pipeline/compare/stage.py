"""The compare stage: two snapshots in the environment frame → clusters, identities, changes.

Steps: C2C both ways → thresholds → candidate points → "not seen ≠ removed" filter →
DBSCAN per side → re-projection with visibility into the side's own capture → merging of
split clusters → hysteresis growth through points above the lower threshold, less the
smeared floor around each foot (skirt pruning), then the band beneath its walls (base
growth) → identification table (identify.py) → names from cross-evidence (the twin, a
move's other end, a swap's place) → evidence that each unidentified cluster is a change
(seen empty, off the other cloud's surface, not part of an object standing in both) →
change types against the twin. The steps before clustering are in candidates.py, a side's
clustering in side_clusters.py, the cross-capture evidence in evidence.py.
Pure: no files, no database; randomness (z-buffer point subsets, spacing samples) is seeded.
"""

from __future__ import annotations

import time
import uuid
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from workers.pipeline.compare.c2c import C2CResult, c2c_both_ways
from workers.pipeline.compare.candidates import (
    Candidates,
    CloudStatsPair,
    DepthMapsPair,
    SideCandidates,
    both_cloud_stats,
    drop_unseen_removed,
    find_candidates,
    on_other_surface,
    unevidenced_added,
)
from workers.pipeline.compare.changes import classify_changes
from workers.pipeline.compare.data import Camera, CaptureData, TwinInstance
from workers.pipeline.compare.evidence import (
    Captures,
    join_split_objects,
    name_at_removals,
    name_by_twin,
    name_move_ends,
    parts_of_standing_objects,
    still_there,
)
from workers.pipeline.compare.files import read_photo
from workers.pipeline.compare.options import PRESETS, CompareOptions
from workers.pipeline.compare.results import ClusterResult, CompareResult, Side
from workers.pipeline.compare.side_clusters import Library, SideInput, side_clusters
from workers.pipeline.compare.thresholds import CloudStats
from workers.pipeline.compare.visibility import DepthMap, render_depth
from workers.pipeline.errors import ComparisonError, InputError
from workers.pipeline.threads import ordered_map

Progress = Callable[[str, float], None]
SIDES: tuple[Side, ...] = ("added", "removed")


def render_depth_maps(
    capture: CaptureData, options: CompareOptions, max_side: int | None = None
) -> list[DepthMap]:
    """One z-buffer per camera of ``capture`` from (a seeded subset of) its own cloud,
    ``max_side`` pixels on its long side (default ``zbuffer_max_side``), each checked
    against the camera's photo where the capture has it and its cloud has colours (unless
    ``seen_colour_tolerance`` is None)."""
    side = options.zbuffer_max_side if max_side is None else max_side
    pts, colors = capture.points_env, capture.colors
    if len(pts) > options.zbuffer_max_points:
        rng = np.random.default_rng(options.seed)
        pick = rng.choice(len(pts), options.zbuffer_max_points, replace=False)
        pts = pts[pick]
        colors = None if colors is None else colors[pick]
    pts32 = np.ascontiguousarray(pts.T, dtype=np.float32)  # (3, N) columns
    tol = options.seen_colour_tolerance
    colors32 = None if colors is None or tol is None else colors.astype(np.float32)

    def render(cam: Camera) -> DepthMap:
        path = capture.photos.get(cam.name)
        if colors32 is None or tol is None or path is None:
            return render_depth(cam, pts32, side, options.zbuffer_fill_px)
        photo = read_photo(path, cam, side)
        return render_depth(cam, pts32, side, options.zbuffer_fill_px, colors32, photo, tol)

    return ordered_map(render, capture.cameras, 0)  # one camera per core at a time


def _check_inputs(classes: Sequence[str], class_diameters_m: Mapping[str, float]) -> None:
    if len(set(classes)) != len(classes) or not all(isinstance(c, str) and c for c in classes):
        raise InputError("classes must be unique non-empty names")
    for name, d in class_diameters_m.items():
        if not (np.isfinite(d) and d > 0):
            raise InputError(f"diameter of {name!r} must be finite and > 0, got {d}")


class _Stopwatch:
    """Wall-clock seconds per step, and the process's CPU seconds (all threads): on a shared
    machine the wall clock measures the load, the CPU time the work."""

    def __init__(self) -> None:
        self.timings: dict[str, float] = {}
        self.cpu: dict[str, float] = {}
        self._wall, self._cpu = time.perf_counter(), time.process_time()

    def lap(self, name: str) -> None:
        """Record the time since the previous lap (or the start) under ``name``."""
        now_wall, now_cpu = time.perf_counter(), time.process_time()
        self.timings[name] = round(now_wall - self._wall, 4)
        self.cpu[name] = round(now_cpu - self._cpu, 4)
        self._wall, self._cpu = now_wall, now_cpu


def _depth_maps(before: CaptureData, after: CaptureData, options: CompareOptions) -> DepthMapsPair:
    """The z-buffers the options need: for occlusion, the seen checks or overlap statistics."""
    overlap = options.stats_region == "overlap"
    need_after = options.use_visibility or options.check_seen_removed or overlap
    need_before = options.use_visibility or options.check_seen_added or overlap
    maps_after = render_depth_maps(after, options) if need_after else None
    maps_before = render_depth_maps(before, options) if need_before else None
    return DepthMapsPair(before=maps_before, after=maps_after)


def _seen_maps(
    before: CaptureData, after: CaptureData, maps: DepthMapsPair, options: CompareOptions
) -> DepthMapsPair:
    """The z-buffers of the seen checks: ``maps`` themselves, or finer ones when
    ``seen_zbuffer_max_side`` asks for them."""
    side = options.seen_zbuffer_max_side
    if side is None or side == options.zbuffer_max_side:
        return maps
    after_maps = render_depth_maps(after, options, side) if options.check_seen_removed else None
    before_maps = render_depth_maps(before, options, side) if options.check_seen_added else None
    return DepthMapsPair(before=before_maps, after=after_maps)


def _side_input(
    side: Side,
    capture: CaptureData,
    found: SideCandidates,
    cloud: CloudStats,
    maps: list[DepthMap] | None,
    first_id: int,
    options: CompareOptions,
) -> SideInput:
    """What clustering one side needs: its candidates, spacing, base band and z-buffers
    (``maps``, the side's own, used only with ``use_visibility``)."""
    return SideInput(
        side=side,
        capture=capture,
        candidates=found.found,
        low=found.low,
        spacing_m=cloud.spacing,
        base_band_m=options.base_band_factor * (found.distances.grow_threshold or 0.0),
        depth_maps=maps if options.use_visibility else None,
        first_id=first_id,
    )


def _both_sides_clusters(
    before: CaptureData,
    after: CaptureData,
    candidates: Candidates,
    clouds: CloudStatsPair,
    maps: DepthMapsPair,
    library: Library,
    options: CompareOptions,
) -> list[ClusterResult]:
    """The added side's clusters (ids from 1), then the removed side's."""
    added = _side_input("added", after, candidates.added, clouds.after, maps.after, 1, options)
    clusters = side_clusters(added, library, options)
    first_id = len(clusters) + 1
    removed = _side_input(
        "removed", before, candidates.removed, clouds.before, maps.before, first_id, options
    )
    clusters += side_clusters(removed, library, options)
    return clusters


def _stats_json(
    before: CaptureData,
    after: CaptureData,
    clouds: CloudStatsPair,
    candidates: Candidates,
    watch: _Stopwatch,
) -> dict[str, Any]:
    """The result's ``stats``: counts, spacing and roughness (metres), timings (seconds)."""
    added, removed = candidates.added, candidates.removed
    roughness = {"before": clouds.before.roughness, "after": clouds.after.roughness}
    return {
        "points": {"before": len(before.points_env), "after": len(after.points_env)},
        "spacing_m": {"before": clouds.before.spacing, "after": clouds.after.spacing},
        "roughness_m": roughness if clouds.lod else None,
        "candidates": {"added": added.n_above, "removed": removed.n_above},
        "candidates_seen": {"added": int(added.found.size), "removed": int(removed.found.size)},
        "timings_s": watch.timings,
        "cpu_s": watch.cpu,
    }


def _unevidenced(
    clusters: Sequence[ClusterResult],
    c2c: C2CResult,
    candidates: Candidates,
    seen_maps: DepthMapsPair,
    both: Captures,
    options: CompareOptions,
) -> set[int]:
    """Ids of unidentified clusters without evidence of a change: the other capture did not
    see the place empty (added side) or the points continue the other cloud's surface."""
    thresholds: dict[str, float] = {
        side: getattr(candidates, side).distances.threshold for side in SIDES
    }
    out = unevidenced_added(
        clusters, c2c.added, thresholds["added"], both.after, seen_maps.before, options
    )
    return out | on_other_surface(clusters, c2c, thresholds, options)


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
    watch = _Stopwatch()

    report("compare.distances", 0.0)
    c2c = c2c_both_ways(before.points_env, after.points_env)
    watch.lap("c2c")
    clouds = both_cloud_stats(c2c, options)
    watch.lap("cloud_stats")

    report("compare.visibility", 0.2)
    maps = _depth_maps(before, after, options)
    watch.lap("zbuffers")
    candidates = find_candidates(c2c, before, after, clouds, maps, options)
    watch.lap("thresholds")
    seen_maps = _seen_maps(before, after, maps, options)
    removed = drop_unseen_removed(candidates.removed, before, seen_maps.after, options)
    candidates = Candidates(added=candidates.added, removed=removed)
    watch.lap("seen_check")

    report("compare.clusters", 0.5)
    reach_m = options.grow_max_diameters * max(class_diameters_m.values(), default=0.0)
    library = Library(classes=classes, class_diameters_m=class_diameters_m, grow_max_m=reach_m)
    clusters = _both_sides_clusters(before, after, candidates, clouds, maps, library, options)
    both = Captures(before, after, maps.before, maps.after, classes)
    # a piece of an object standing in both captures is no change, named or not
    pieces = parts_of_standing_objects(clusters, both, options)
    clusters = name_by_twin(clusters, twin, class_diameters_m, options)
    clusters = name_move_ends(clusters, class_diameters_m, both, options, pieces)
    clusters = name_at_removals(clusters, class_diameters_m, options)
    clusters, parts = join_split_objects(clusters, class_diameters_m, options, skip=pieces)
    pieces |= parts
    watch.lap("clusters_identify")

    report("compare.changes", 0.9)
    unevidenced = _unevidenced(clusters, c2c, candidates, seen_maps, both, options) | pieces
    there = still_there(clusters, both, options)
    try:
        changes = classify_changes(
            clusters,
            twin,
            class_diameters_m,
            options,
            make_id,
            not_changes=unevidenced,
            still_there=there,
        )
    except ValueError as exc:  # linear_sum_assignment on degenerate input
        raise ComparisonError(f"could not pair changes: {exc}") from exc
    watch.lap("changes")
    report("compare.changes", 1.0)
    return CompareResult(
        options=options,
        distances={"added": candidates.added.distances, "removed": candidates.removed.distances},
        clusters=tuple(clusters),
        changes=tuple(changes),
        added_distances_m=c2c.added,
        removed_distances_m=c2c.removed,
        stats=_stats_json(before, after, clouds, candidates, watch),
    )
