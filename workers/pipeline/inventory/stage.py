"""The inventory stage: every library object a reconstructed snapshot shows, changed or not.

Steps: the support surfaces (:mod:`~workers.pipeline.inventory.supports`) → the points that
stand on them (above the support's noise band, below the tallest library object) → the
compare stage's clustering, re-projection, merging and identification of those points
(:func:`workers.pipeline.compare.side_clusters.side_clusters`: the same metric and threshold
as a changed cluster) → the pose stage's estimate and re-projection check of each
identified segment (:func:`workers.pipeline.pose.posing.pose_change`) → one object per
instance (two segments of one class closer than ``duplicate_diameters`` are one).

Everything in the environment frame (z up), metres; poses are 4×4 ``env_from_object``.
Pure: no files, no database; deterministic for given options (their seeds).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from workers.pipeline.compare.clusters import dbscan, groups_from_labels
from workers.pipeline.compare.data import CaptureData
from workers.pipeline.compare.evidence import points_table
from workers.pipeline.compare.options import CompareOptions
from workers.pipeline.compare.results import Change, ClusterResult
from workers.pipeline.compare.side_clusters import Library, SideInput, side_clusters
from workers.pipeline.compare.stage import render_depth_maps
from workers.pipeline.compare.visibility import DepthMap
from workers.pipeline.errors import InputError
from workers.pipeline.geometry import transform_points
from workers.pipeline.inventory.options import INVENTORY_PRESETS, InventoryOptions
from workers.pipeline.inventory.supports import Support, find_supports, standing_heights
from workers.pipeline.model import PreparedModel
from workers.pipeline.pose.crop import SceneCloud
from workers.pipeline.pose.fit import median_spacing_m
from workers.pipeline.pose.options import PoseOptions
from workers.pipeline.pose.photo_edges import CaptureSight
from workers.pipeline.pose.posing import pose_change
from workers.pipeline.threads import ordered_map

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
Progress = Callable[[str, float], None]


@dataclass(frozen=True, eq=False)
class InventoryObject:
    """One library object found in the snapshot.

    ``env_from_object`` (4, 4) metres or None (no prepared model, or registration failed);
    ``pose_quality`` the pose stage's figures (``verified``, ``reasons``, ``reprojection``
    ...) or None without a pose; ``identification`` the compare stage's figures of its
    class (``metric``, ``iou``, ``overlaps``, ``occurrences``); ``centroid_env`` (3,) the
    posed model's centre (else the segment's); ``support`` the surface it stands on."""

    object_name: str
    class_id: int
    env_from_object: FloatArray | None
    pose_quality: dict[str, Any] | None
    identification: dict[str, Any]
    centroid_env: FloatArray
    cluster: dict[str, Any]
    support: str | None

    @property
    def verified(self) -> bool:
        return bool(self.pose_quality and self.pose_quality.get("verified"))

    def to_json(self) -> dict[str, Any]:
        return {
            "object": self.object_name,
            "class_id": self.class_id,
            "pose": None if self.env_from_object is None else self.env_from_object.tolist(),
            "pose_quality": self.pose_quality,
            "identification": self.identification,
            "centroid_env": self.centroid_env.tolist(),
            "cluster": self.cluster,
            "support": self.support,
        }


@dataclass(frozen=True, eq=False)
class InventoryResult:
    """``objects`` found (in segment order); ``rejected`` identified segments left out
    (with ``reason``); ``supports`` the surfaces found; ``stats`` counts and timings."""

    options: InventoryOptions
    objects: tuple[InventoryObject, ...]
    rejected: tuple[dict[str, Any], ...]
    supports: tuple[Support, ...]
    stats: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {
            "options": self.options.to_json(),
            "objects": [o.to_json() for o in self.objects],
            "rejected": list(self.rejected),
            "supports": [s.to_json() for s in self.supports],
            "stats": dict(self.stats),
        }


def _check(classes: Sequence[str], class_diameters_m: Mapping[str, float]) -> None:
    if len(set(classes)) != len(classes) or not all(isinstance(c, str) and c for c in classes):
        raise InputError("classes must be unique non-empty names")
    for name, d in class_diameters_m.items():
        if name not in classes:
            raise InputError(f"library object {name!r} is not one of the classes")
        if not (np.isfinite(d) and d > 0):
            raise InputError(f"diameter of {name!r} must be finite and > 0, got {d}")


def _standing(
    points: FloatArray, supports: Sequence[Support], max_height_m: float, o: InventoryOptions
) -> tuple[IntArray, IntArray | None, IntArray]:
    """Indices of the points standing on a support (strict band) and of those within the
    growth band (None: no growth), and each point's support index (−1: none)."""
    heights, owner = standing_heights(points, list(supports))
    noise = np.array([s.noise_m for s in supports] + [0.0])[owner]
    band = np.maximum(o.band_min_m, o.band_sigmas * noise)
    ok = np.isfinite(heights) & (heights < max_height_m)
    strict = np.flatnonzero(ok & (heights > band))
    low = None
    if o.grow_band_factor > 0:
        low = np.flatnonzero(ok & (heights > o.grow_band_factor * band))
    return strict, low, owner


def _not_oversized(
    points: FloatArray, idx: IntArray, radius_m: float, max_extent_m: float, c: Any
) -> IntArray:
    """``idx`` less the connected segments longer than ``max_extent_m`` (walls seen near
    the floor, table and shelf sides): the compare stage's DBSCAN with its settings."""
    if len(idx) == 0:
        return idx
    labels = dbscan(points[idx], radius_m, c.cluster_min_samples, c.cluster_min_points)
    keep = [
        idx[g]
        for g in groups_from_labels(labels)
        if float(np.max(np.ptp(points[idx[g]], axis=0))) <= max_extent_m
    ]
    return np.sort(np.concatenate(keep)) if keep else np.zeros(0, dtype=np.int64)


def _segment_json(cluster: ClusterResult) -> dict[str, Any]:
    return {**cluster.summary_json(), "metrics": dict(cluster.metrics)}


@dataclass
class _Stopwatch:
    """Wall seconds per step."""

    timings: dict[str, float] = field(default_factory=dict)
    t0: float = field(default_factory=time.perf_counter)

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.timings[name] = round(now - self.t0, 3)
        self.t0 = now


@dataclass(frozen=True, eq=False)
class _Segments:
    """What segmentation leaves for posing: the supports, each point's support index, the
    segments (identified or not), the z-buffers and the counts of the stats."""

    supports: tuple[Support, ...]
    owner: IntArray
    segments: list[ClusterResult]
    maps: list[DepthMap]
    counts: dict[str, Any]


def _segment(
    capture: CaptureData,
    classes: Sequence[str],
    class_diameters_m: Mapping[str, float],
    options: InventoryOptions,
    report: Progress,
    watch: _Stopwatch,
) -> _Segments | None:
    """Supports → standing points → the compare stage's clusters and identification; None
    when the cloud has no support."""
    points = capture.points_env
    compare_options = options.compare_options()
    max_d = max(class_diameters_m.values())
    report("inventory.supports", 0.0)
    supports = find_supports(points, max_d, options)
    watch.lap("supports")
    if not supports:
        return None
    strict, low, owner = _standing(points, supports, options.max_height_diameters * max_d, options)
    spacing = median_spacing_m(points, compare_options.spacing_sample, options.seed)
    radius = compare_options.cluster_radius_factor * spacing
    candidates = _not_oversized(
        points, strict, radius, options.max_extent_diameters * max_d, compare_options
    )
    watch.lap("standing")
    report("inventory.segments", 0.2)
    maps = render_depth_maps(capture, compare_options)
    watch.lap("zbuffers")
    library = Library(
        classes=list(classes),
        class_diameters_m=dict(class_diameters_m),
        grow_max_m=compare_options.grow_max_diameters * max_d,
    )
    side = SideInput(
        side="added",
        capture=capture,
        candidates=candidates,
        low=low,
        spacing_m=spacing,
        base_band_m=0.0,
        depth_maps=maps if compare_options.use_visibility else None,
        first_id=1,
    )
    segments = side_clusters(side, library, compare_options) if len(candidates) else []
    watch.lap("segments_identify")
    counts = {
        "spacing_m": spacing,
        "standing_points": len(strict),
        "candidate_points": len(candidates),
        "segments": len(segments),
    }
    return _Segments(tuple(supports), owner, segments, maps, counts)


def _support_of(cluster: ClusterResult, seg: _Segments) -> str | None:
    """The support most of the cluster's points stand on."""
    votes = seg.owner[cluster.indices]
    votes = votes[votes >= 0]
    return seg.supports[int(np.bincount(votes).argmax())].name if len(votes) else None


def _weakly_named(
    segments: Sequence[ClusterResult], diameters: Mapping[str, float], c: CompareOptions
) -> dict[ClusterResult, str]:
    """The segments no class names whose best class (one with a model) scores at least
    ``twin_identify_threshold``, with that class: a flat object's segment carries the smear
    around its foot, a box looser than the object's own (none when that option is None)."""
    if c.twin_identify_threshold is None:
        return {}
    out: dict[ClusterResult, str] = {}
    for cluster in segments:
        scores = {k: v for k, v in cluster.metrics.items() if k in diameters}
        if cluster.object_name is None and scores:
            best = max(scores, key=lambda k: scores[k])
            if scores[best] >= c.twin_identify_threshold:
                out[cluster] = best
    return out


def _maps(seg: _Segments, c: CompareOptions) -> list[DepthMap] | None:
    return seg.maps if c.use_visibility else None


def _weak_reason(ident: Mapping[str, Any], name: str, c: CompareOptions) -> str:
    posed = ident.get("model_metric")
    model = f"no pose as {name}" if posed is None else f"posed {name} {posed:.2f}"
    segment = float(ident.get("metric", 0.0))
    return f"named by no class: segment {segment:.2f}, {model} < {c.identify_threshold}"


@dataclass(frozen=True)
class _Posing:
    """What every segment's pose shares (read only while the segments are posed)."""

    capture: CaptureData
    classes: Sequence[str]
    seg: _Segments
    weak: Mapping[ClusterResult, str]
    prepared: Mapping[str, PreparedModel]
    scene: SceneCloud | None
    sight: CaptureSight
    options: InventoryOptions
    compare_options: CompareOptions
    pose_options: PoseOptions


def _pose_segment(
    p: _Posing, cluster: ClusterResult, name: str
) -> tuple[InventoryObject | None, dict[str, Any] | None]:
    """One identified segment posed and checked: (the object, None) or (None, why not)."""
    compare_options = p.compare_options
    ident = cluster.identification_json(name)
    ident.pop("object", None)
    pose: dict[str, Any] = {}
    model = p.prepared.get(name)
    class_id = list(p.classes).index(name)
    if model is not None and p.scene is not None:
        change = Change(f"segment-{cluster.id}", "added", name, None, cluster)
        pose = pose_change(change, model, p.scene, p.sight, class_id, p.pose_options)
    quality = pose.get("pose_quality")
    passed = bool(quality and (quality.get("reprojection") or {}).get("passed"))
    reasons = [str(r) for r in (quality or {}).get("reasons") or ["no pose"]]
    unnamed = False  # a weakly named segment counts only when its posed model names it
    if cluster in p.weak:
        if pose.get("pose") is not None and model is not None:
            posed = transform_points(np.asarray(pose["pose"]), model.points)
            maps = _maps(p.seg, compare_options)
            table = points_table([posed], p.capture, maps, p.classes, compare_options)
            ident["model_metric"] = float(table.metric[0, class_id])
        unnamed = ident.get("model_metric", 0.0) < compare_options.identify_threshold
        if unnamed:
            reasons = [_weak_reason(ident, name, compare_options), *reasons]
    if unnamed or (p.options.require_reprojection and model is not None and not passed):
        why = {"object": name, "identification": ident, "cluster": _segment_json(cluster)}
        return None, why | {"reason": "; ".join(reasons)}
    return (
        InventoryObject(
            object_name=name,
            class_id=class_id,
            env_from_object=None if pose.get("pose") is None else np.asarray(pose["pose"]),
            pose_quality=quality,
            identification=ident,
            centroid_env=np.asarray(pose.get("centroid_env", cluster.centroid), float),
            cluster=_segment_json(cluster),
            support=_support_of(cluster, p.seg),
        ),
        None,
    )


def _pose_segments(
    capture: CaptureData,
    classes: Sequence[str],
    class_diameters_m: Mapping[str, float],
    load_model: Callable[[str], PreparedModel],
    seg: _Segments,
    options: InventoryOptions,
    report: Progress,
) -> tuple[list[InventoryObject], list[dict[str, Any]]]:
    """Each identified segment posed as the pose stage poses a change (the pose options'
    ``threads`` at once); those whose posed model misses the detector's boxes are rejected
    (``require_reprojection``)."""
    compare_options, pose_options = options.compare_options(), options.pose_options()
    weak = _weakly_named(seg.segments, class_diameters_m, compare_options)
    named = [(c, str(c.object_name)) for c in seg.segments if c.object_name is not None]
    named += [(c, name) for c, name in weak.items()]
    scene = SceneCloud.create(capture.points_env, colors=capture.colors) if named else None
    wanted = dict.fromkeys(name for _, name in named if name in class_diameters_m)
    prepared = {name: load_model(name) for name in wanted} if scene is not None else {}
    sight = CaptureSight(capture, seg.maps)
    posing = _Posing(
        capture, classes, seg, weak, prepared, scene, sight, options, compare_options, pose_options
    )
    report("inventory.pose", 0.4)
    outcomes = ordered_map(
        lambda item: _pose_segment(posing, *item),
        named,
        pose_options.threads,
        lambda k: report("inventory.pose", 0.4 + 0.6 * k / len(named)),
    )
    found = [obj for obj, _ in outcomes if obj is not None]
    return found, [why for _, why in outcomes if why is not None]


def take_inventory(
    capture: CaptureData,
    classes: Sequence[str],
    class_diameters_m: Mapping[str, float],
    load_model: Callable[[str], PreparedModel],
    options: InventoryOptions = INVENTORY_PRESETS["default"],
    progress: Progress | None = None,
) -> InventoryResult:
    """Every library object ``capture`` shows (environment frame, z up, metres).

    ``classes[i]`` is detector class id i; ``class_diameters_m`` the diameters of the
    library objects that have a prepared model (their segments are posed;
    ``load_model(name)`` is called at most once per class; none: nothing is found).
    ``progress(stage, fraction)`` may raise Cancelled. Raises ShapeError/InputError for bad
    inputs.
    """
    report: Progress = progress or (lambda _stage, _fraction: None)
    _check(classes, class_diameters_m)
    watch = _Stopwatch()
    points = capture.points_env
    stats: dict[str, Any] = {"points": len(points), "timings_s": watch.timings}
    if len(points) < 10 or not class_diameters_m:
        return InventoryResult(options, (), (), (), stats)
    seg = _segment(capture, classes, class_diameters_m, options, report, watch)
    if seg is None:
        return InventoryResult(options, (), (), (), stats)
    found, rejected = _pose_segments(
        capture, classes, class_diameters_m, load_model, seg, options, report
    )
    objects, duplicates = _one_per_instance(found, class_diameters_m, options)
    rejected.extend(duplicates)
    watch.lap("pose")
    report("inventory.pose", 1.0)
    stats.update(
        seg.counts,
        identified_segments=sum(1 for c in seg.segments if c.object_name is not None),
        objects=len(objects),
    )
    return InventoryResult(options, tuple(objects), tuple(rejected), seg.supports, stats)


def _rank(obj: InventoryObject) -> tuple[float, float]:
    return (1.0 if obj.verified else 0.0, float(obj.identification.get("metric", 0.0)))


def _one_per_instance(
    found: Sequence[InventoryObject], diameters: Mapping[str, float], o: InventoryOptions
) -> tuple[list[InventoryObject], list[dict[str, Any]]]:
    """Objects of one class closer than ``duplicate_diameters`` × its diameter are one
    (a split segment): the verified one, else the best identified, is kept."""
    kept: list[InventoryObject] = []
    dropped: list[dict[str, Any]] = []
    for obj in sorted(found, key=_rank, reverse=True):
        reach = o.duplicate_diameters * diameters.get(obj.object_name, 0.0)
        twin = next(
            (
                k
                for k in kept
                if k.object_name == obj.object_name
                and float(np.linalg.norm(k.centroid_env - obj.centroid_env)) < reach
            ),
            None,
        )
        if twin is None:
            kept.append(obj)
        else:
            dropped.append({**obj.to_json(), "reason": "duplicate of a better segment"})
    order = {id(o_): i for i, o_ in enumerate(found)}
    kept.sort(key=lambda k: order[id(k)])
    return kept, dropped
