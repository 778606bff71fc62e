"""Steps of the compare stage before clustering: cloud statistics, each side's thresholds
and candidate points, and the "not seen ≠ changed" evidence from the other capture.

Indices are into the side's own cloud (``after`` for "added", ``before`` for "removed");
distances in metres. Randomness (statistics samples) is seeded by ``options.seed``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from workers.pipeline.compare.c2c import C2CResult
from workers.pipeline.compare.data import CaptureData
from workers.pipeline.compare.options import CompareOptions
from workers.pipeline.compare.results import ClusterResult
from workers.pipeline.compare.thresholds import (
    CloudStats,
    DistanceStats,
    cloud_stats,
    distance_stats,
)
from workers.pipeline.compare.visibility import DepthMap, covered_mask, depth_votes

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: neighbours of the other cloud the local surface plane of :func:`on_other_surface` is
#: fitted to (as the roughness of a lod threshold)
SURFACE_NEIGHBOURS = 16


@dataclass(frozen=True)
class CloudStatsPair:
    """Spacing and roughness of both clouds; ``lod``: whether roughness was measured (some
    threshold is a level of detection), else the roughness is nan."""

    before: CloudStats
    after: CloudStats
    lod: bool


@dataclass(frozen=True)
class DepthMapsPair:
    """One z-buffer per camera of each capture, from its own cloud (None: not needed)."""

    before: list[DepthMap] | None
    after: list[DepthMap] | None


@dataclass(frozen=True)
class SideCandidates:
    """One side's thresholds and candidate points.

    ``found`` (n,) indices of the points above ``distances.threshold`` (for "removed",
    after the seen-as-empty filter when it ran); ``n_above`` how many were above the
    threshold before that filter; ``low`` the points above the grow threshold (None: no
    hysteresis growth).
    """

    distances: DistanceStats
    found: IntArray
    n_above: int
    low: IntArray | None


@dataclass(frozen=True)
class Candidates:
    """Both sides' candidates: "added" from the after cloud, "removed" from the before one."""

    added: SideCandidates
    removed: SideCandidates


def both_cloud_stats(c2c: C2CResult, options: CompareOptions) -> CloudStatsPair:
    """Spacing (and, for a lod threshold, roughness) of both clouds from seeded samples."""
    grow = options.grow_threshold
    specs = [options.threshold] + ([grow] if grow is not None else [])
    nb = max(spec.neighbours for spec in specs)
    lod = any(spec.kind == "lod" for spec in specs)
    before = cloud_stats(c2c.tree_before, options.spacing_sample, nb, options.seed, lod)
    after = cloud_stats(c2c.tree_after, options.spacing_sample, nb, options.seed, lod)
    return CloudStatsPair(before=before, after=after, lod=lod)


def _sample_indices(n: int, size: int, seed: int) -> IntArray:
    """All of range(n), or a sorted seeded sample of ``size`` of them."""
    if n <= size:
        return np.arange(n, dtype=np.int64)
    rng = np.random.default_rng(seed)
    return np.sort(rng.choice(n, size=size, replace=False)).astype(np.int64)


def side_distance_stats(
    dist: FloatArray,
    own: CaptureData,
    other_maps: list[DepthMap] | None,
    compared: CloudStats,
    reference: CloudStats,
    registration_m: float,
    options: CompareOptions,
) -> DistanceStats:
    """Statistics and thresholds of one side's (N,) C2C distances (metres).

    With ``stats_region`` "overlap" and the other capture's z-buffers, only the points the
    other capture looked at count (a seeded sample), unless fewer than
    ``cluster_min_points`` of them do. The grow threshold is capped at the threshold.
    """
    region, sample = "all", dist
    if options.stats_region == "overlap" and other_maps:
        idx = _sample_indices(len(dist), options.stats_sample, options.seed)
        tol = (options.depth_tolerance_m, options.depth_tolerance_px)
        covered = covered_mask(own.points_env[idx], other_maps, *tol)
        if np.count_nonzero(covered) >= options.cluster_min_points:
            region, sample = "overlap", dist[idx[covered]]
    out = distance_stats(sample, options.threshold, compared, reference, registration_m, region)
    grow = options.grow_threshold
    if grow is None:
        return out
    low = distance_stats(sample, grow, compared, reference, registration_m, region).threshold
    return dataclasses.replace(out, grow_threshold=min(low, out.threshold))


def _side_candidates(dist: FloatArray, stats: DistanceStats) -> SideCandidates:
    found = np.flatnonzero(dist > stats.threshold).astype(np.int64)
    low = None if stats.grow_threshold is None else np.flatnonzero(dist > stats.grow_threshold)
    return SideCandidates(distances=stats, found=found, n_above=int(found.size), low=low)


def find_candidates(
    c2c: C2CResult,
    before: CaptureData,
    after: CaptureData,
    clouds: CloudStatsPair,
    maps: DepthMapsPair,
    options: CompareOptions,
) -> Candidates:
    """Thresholds of both sides and the points above them (and above the grow threshold).

    The registration error is ``hypot`` of the captures' alignment residuals (metres).
    """
    reg = float(np.hypot(before.alignment_residual_m, after.alignment_residual_m))
    stats_added = side_distance_stats(
        c2c.added, after, maps.before, clouds.after, clouds.before, reg, options
    )
    stats_removed = side_distance_stats(
        c2c.removed, before, maps.after, clouds.before, clouds.after, reg, options
    )
    return Candidates(
        added=_side_candidates(c2c.added, stats_added),
        removed=_side_candidates(c2c.removed, stats_removed),
    )


def drop_unseen_removed(
    removed: SideCandidates,
    before: CaptureData,
    maps_after: list[DepthMap] | None,
    options: CompareOptions,
) -> SideCandidates:
    """ "Not seen ≠ removed": keep the removed candidates that at least ``min_seen_views`` of
    the after capture's cameras see as empty space (all of them when the check is off).

    Growth points (``low``) need no such evidence: the seeds decide which clusters exist,
    growth only completes them, and a removed object's base lies within the depth
    tolerance of the floor seen behind it, so it could never be seen as empty.
    """
    if not (options.check_seen_removed and maps_after is not None):
        return removed
    tol = (options.seen_tolerance_m, options.seen_tolerance_px)
    seen = depth_votes(before.points_env[removed.found], maps_after, *tol)[0]
    return dataclasses.replace(removed, found=removed.found[seen >= options.min_seen_views])


def unevidenced_added(
    clusters: Sequence[ClusterResult],
    added_distances_m: FloatArray,
    threshold_m: float,
    after: CaptureData,
    maps_before: list[DepthMap] | None,
    options: CompareOptions,
) -> set[int]:
    """Ids of unidentified added clusters without evidence of a change: fewer than
    ``min_seen_fraction`` of their points above the strict threshold ``threshold_m`` lie
    where ≥ ``min_seen_views`` of the before capture's cameras saw empty space.

    Only unidentified clusters need this evidence (a hole in the old cloud is not an
    addition); an identified object can stand where the old capture could not look, e.g.
    inside a swapped object's volume. Grown points lie close to old surfaces by
    construction, hence the strict threshold.
    """
    unevidenced: set[int] = set()
    if not (options.check_seen_added and maps_before is not None):
        return unevidenced
    unknown = [c for c in clusters if c.side == "added" and c.object_name is None]
    strict = [c.indices[added_distances_m[c.indices] > threshold_m] for c in unknown]
    if not unknown:
        return unevidenced
    # one pass over the cameras for all of them
    tol = (options.seen_tolerance_m, options.seen_tolerance_px)
    seen = depth_votes(after.points_env[np.concatenate(strict)], maps_before, *tol)[0]
    owner = np.repeat(np.arange(len(unknown)), [len(idx) for idx in strict])
    n_seen = np.bincount(owner[seen >= options.min_seen_views], minlength=len(unknown))
    for c, idx, k in zip(unknown, strict, n_seen, strict=True):
        if k < options.min_seen_fraction * len(idx):
            unevidenced.add(c.id)
    return unevidenced


def surface_distances(points_env: FloatArray, other: cKDTree) -> FloatArray:
    """Distance (N,) metres of (N, 3) points to the other cloud's local surface: the PCA
    plane through their ``SURFACE_NEIGHBOURS`` nearest points of the cloud in ``other``."""
    k = min(SURFACE_NEIGHBOURS, other.n)
    _, nn = other.query(points_env, k=k, workers=-1)
    nb = np.asarray(other.data)[nn.reshape(len(points_env), k)]  # (N, k, 3)
    centre = nb.mean(axis=1)
    centred = nb - centre[:, None, :]
    normal = np.linalg.eigh(np.einsum("nki,nkj->nij", centred, centred))[1][:, :, 0]
    return np.asarray(np.abs(np.einsum("ni,ni->n", points_env - centre, normal)))


def on_other_surface(
    clusters: Sequence[ClusterResult],
    c2c: C2CResult,
    thresholds_m: Mapping[str, float],
    options: CompareOptions,
) -> set[int]:
    """Ids of unidentified clusters that continue the other cloud's surface: fewer than
    ``min_seen_fraction`` of their points above the strict threshold (``thresholds_m`` per
    side) lie farther than it from the other cloud's local plane
    (:func:`surface_distances`). Such points are far from every point of the other cloud
    only because it has a hole there (a floor patch stereo did not fill), not because
    anything stands or stood there. Sides follow ``check_seen_added`` / ``check_seen_removed``.
    """
    out: set[int] = set()
    for side, distances, own_tree, other, on in (
        ("added", c2c.added, c2c.tree_after, c2c.tree_before, options.check_seen_added),
        ("removed", c2c.removed, c2c.tree_before, c2c.tree_after, options.check_seen_removed),
    ):
        if not on:
            continue
        own = np.asarray(own_tree.data)
        threshold = thresholds_m[side]
        for c in clusters:
            if c.side != side or c.object_name is not None:
                continue
            strict = c.indices[distances[c.indices] > threshold]
            if strict.size == 0:
                continue
            off = surface_distances(own[strict], other) > threshold
            if np.count_nonzero(off) < options.min_seen_fraction * strict.size:
                out.add(c.id)
    return out
