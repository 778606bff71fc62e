"""Density clustering of changed points and merging of clusters that belong to one object.

Clustering is DBSCAN over a radius graph: a point with ≥ ``min_samples`` points (itself
included) within ``radius`` is a core point; connected core points form a cluster; a
non-core point within ``radius`` of a core point joins that core's cluster; the rest is
noise. Clusters under ``min_points`` points are specks and dropped. The radius follows the
cloud: ``radius = factor × median nearest-neighbour spacing``.

Hysteresis growth (as Canny's edge linking): clusters found at the strict threshold take the
points above a lower threshold that they reach through chains of ``radius`` hops, no
further than a geodesic ``max_distance``. It gives back an object's base, whose points lie
close to the old floor and fall under the strict threshold, without letting noise seed a
cluster of its own.

Skirt pruning then drops what growth took of the floor around an object's foot: stereo
smears depth across the object's silhouette there, so a thin ring of floor points floats
above the old floor by more than the lower threshold. A grown point with none of its
cluster's points above it, close to the cluster's seeds, is such a point; an object's own
walls have points above them, and a low part that reaches further out keeps its far end.

Base growth then completes what even the lower threshold cuts off: an object's lowest band,
within the growth threshold of the floor it stands on (its distance to the other capture's
floor is its height). A cluster takes the points directly beneath its own points, in
vertical columns of a small horizontal radius, down to a fixed band below them. Only
beneath its walls (points with a point of the cluster above them, as for skirt pruning): a
wall goes on down to the floor, but beneath the smear that stereo leaves at the foot (a
fillet sloping out from the wall, seeds too where it rises above the strict threshold)
lies only floor. The environment frame's +z is up (the convention
:func:`workers.pipeline.pose.estimate_pose` uses for ``up_env``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, dijkstra
from scipy.spatial import cKDTree

from workers.pipeline.errors import ComparisonError
from workers.pipeline.geometry import as_points

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


def dbscan(
    points_env: ArrayLike, radius: float, min_samples: int = 4, min_points: int = 30
) -> IntArray:
    """Cluster labels (N,) of (N, 3) points: 0, 1, … by decreasing size, −1 for noise/specks.

    ``radius`` metres (> 0). Raises ComparisonError for a non-positive radius.
    """
    pts = as_points(points_env, "points_env")
    n = len(pts)
    if not radius > 0:
        raise ComparisonError(f"cluster radius must be > 0, got {radius}")
    labels = np.full(n, -1, dtype=np.int64)
    if n == 0:
        return labels
    tree = cKDTree(pts, balanced_tree=False, compact_nodes=False)
    pairs = np.asarray(tree.query_pairs(radius, output_type="ndarray"), dtype=np.int64)
    pairs = pairs.reshape(-1, 2)
    counts = 1 + np.bincount(pairs.ravel(), minlength=n)
    core = counts >= min_samples
    cc = core[pairs[:, 0]] & core[pairs[:, 1]]
    core_pairs = pairs[cc]
    graph = coo_matrix(
        (np.ones(len(core_pairs), dtype=np.int8), (core_pairs[:, 0], core_pairs[:, 1])),
        shape=(n, n),
    )
    _, comp = connected_components(graph, directed=False)
    raw = np.where(core, comp, -1).astype(np.int64)
    # border points: a non-core point joins the cluster of (any) core neighbour
    border = core[pairs[:, 0]] ^ core[pairs[:, 1]]
    bp = pairs[border]
    core_end = np.where(core[bp[:, 0]], bp[:, 0], bp[:, 1])
    other_end = np.where(core[bp[:, 0]], bp[:, 1], bp[:, 0])
    raw[other_end] = comp[core_end]
    valid = raw >= 0
    if not np.any(valid):
        return labels
    uniq, inverse, sizes = np.unique(raw[valid], return_inverse=True, return_counts=True)
    keep = sizes >= min_points
    order = np.argsort(-sizes, kind="stable")
    rank = np.full(len(uniq), -1, dtype=np.int64)
    kept_order = order[keep[order]]
    rank[kept_order] = np.arange(len(kept_order))
    labels[valid] = rank[inverse]
    return labels


def groups_from_labels(labels: IntArray, max_clusters: int | None = None) -> list[IntArray]:
    """Point indices of each cluster label 0, 1, … (at most ``max_clusters``, largest first)."""
    n_labels = int(labels.max()) + 1 if labels.size else 0
    if max_clusters is not None:
        n_labels = min(n_labels, max_clusters)
    order = np.argsort(labels, kind="stable")
    sorted_labels = labels[order]
    starts = np.searchsorted(sorted_labels, np.arange(n_labels), side="left")
    ends = np.searchsorted(sorted_labels, np.arange(n_labels), side="right")
    return [order[s:e].astype(np.int64) for s, e in zip(starts, ends, strict=True)]


def _near_voxels(points: FloatArray, seeds: FloatArray, cell: float) -> NDArray[np.bool_]:
    """Mask (N,) of ``points`` in a voxel of side ``cell`` that is, or touches, a voxel
    holding one of ``seeds``: a superset of the points within ``cell`` of a seed."""
    if len(points) == 0 or len(seeds) == 0:
        return np.zeros(len(points), dtype=bool)
    origin = seeds.min(axis=0) - 2 * cell
    seed_vox = np.unique(np.floor((seeds - origin) / cell).astype(np.int64), axis=0)
    dims = seed_vox.max(axis=0) + 3
    offsets = np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing="ij"), -1).reshape(-1, 3)
    near = (seed_vox[:, None, :] + offsets[None, :, :]).reshape(-1, 3)
    near_keys = np.unique(np.ravel_multi_index(near.T, dims))
    vox = np.floor((points - origin) / cell).astype(np.int64)
    inside = np.all((vox >= 0) & (vox < dims), axis=1)
    mask = np.zeros(len(points), dtype=bool)
    keys = np.ravel_multi_index(vox[inside].T, dims)
    mask[np.flatnonzero(inside)] = np.isin(keys, near_keys)
    return mask


def grow_groups(
    groups: Sequence[IntArray],
    points_env: ArrayLike,
    low: ArrayLike,
    radius: float,
    max_distance: float,
) -> list[IntArray]:
    """Each group of indices into (N, 3) ``points_env`` grown through the indices ``low``.

    A ``low`` point joins the group it reaches by hops of ≤ ``radius`` metres through
    ``low`` points, with a path length ≤ ``max_distance`` metres from the group's points;
    a point reached by several groups joins the nearest. Returns the grown groups
    (sorted indices; each a superset of its input). Raises ComparisonError for a
    non-positive radius.
    """
    pts = as_points(points_env, "points_env")
    if not radius > 0:
        raise ComparisonError(f"growth radius must be > 0, got {radius}")
    if not groups or max_distance <= 0:
        return [np.sort(g) for g in groups]
    seeds = np.concatenate(groups).astype(np.int64)
    owner = np.repeat(np.arange(len(groups)), [len(g) for g in groups])
    is_extra = np.zeros(len(pts), dtype=bool)
    is_extra[np.asarray(low, dtype=np.int64)] = True
    is_extra[seeds] = False
    extra = np.flatnonzero(is_extra)
    # a path is never shorter than the straight line: keep the points within max_distance
    # of a seed; first cheaply, those in a voxel (side max_distance) next to a seed's voxel
    extra = extra[_near_voxels(pts[extra], pts[seeds], max_distance)]
    if extra.size:
        near, _ = cKDTree(pts[seeds]).query(pts[extra], distance_upper_bound=max_distance)
        extra = extra[np.isfinite(near)]
    if extra.size == 0:
        return [np.sort(g) for g in groups]
    nodes = np.concatenate([seeds, extra])
    n_seeds = len(seeds)
    tree = cKDTree(pts[nodes], balanced_tree=False, compact_nodes=False)
    pairs = np.asarray(tree.query_pairs(radius, output_type="ndarray"), dtype=np.int64)
    pairs = pairs.reshape(-1, 2)
    pairs = pairs[(pairs[:, 0] >= n_seeds) | (pairs[:, 1] >= n_seeds)]  # seed–seed: no use
    weight = np.linalg.norm(pts[nodes[pairs[:, 0]]] - pts[nodes[pairs[:, 1]]], axis=1)
    graph = coo_matrix(
        (np.maximum(weight, 1e-12), (pairs[:, 0], pairs[:, 1])), shape=(len(nodes),) * 2
    ).tocsr()
    _, _, source = dijkstra(
        graph,
        directed=False,
        indices=np.arange(n_seeds),
        min_only=True,
        limit=max_distance,
        return_predecessors=True,
    )
    reached = np.flatnonzero(source[n_seeds:] >= 0)
    label = owner[source[n_seeds:][reached]]
    grown_idx = extra[reached]
    return [
        np.sort(np.concatenate([g, grown_idx[label == k]])).astype(np.int64)
        for k, g in enumerate(groups)
    ]


def extent(points_env: FloatArray) -> float:
    """Diagonal of the axis-aligned bounding box of (N, 3) points, metres (0 for N < 2)."""
    if len(points_env) < 2:
        return 0.0
    return float(np.linalg.norm(points_env.max(axis=0) - points_env.min(axis=0)))


def merge_groups(
    groups: Sequence[IntArray],
    points_env: FloatArray,
    assigned: Sequence[Mapping[int, tuple[int, str]]],
    class_diameters_m: Mapping[str, float],
    shared_fraction: float = 0.5,
    size_margin: float = 1.25,
) -> list[list[int]]:
    """Which clusters to merge: a partition of ``range(len(groups))`` into merged sets.

    ``assigned[c]`` maps an image index to the detection (index, class name) whose box
    contains cluster c's re-projection in that image. Two clusters are candidates when, over
    the images where both are boxed, they fall in the same detection in at least
    ``shared_fraction`` of them; a merge is accepted only if the merged points' bounding-box
    diagonal stays within ``size_margin ×`` the diameter of that detection class (classes
    without a known diameter never merge). Candidates are merged greedily, best first.
    """
    n = len(groups)
    candidates: list[tuple[float, int, int, str]] = []
    for a in range(n):
        for b in range(a + 1, n):
            common = set(assigned[a]) & set(assigned[b])
            if not common:
                continue
            shared = [i for i in common if assigned[a][i][0] == assigned[b][i][0]]
            frac = len(shared) / len(common)
            if not shared or frac < shared_fraction:
                continue
            names = [assigned[a][i][1] for i in shared]
            name = max(set(names), key=names.count)
            candidates.append((frac * len(shared), a, b, name))
    candidates.sort(key=lambda c: -c[0])
    parent = list(range(n))
    members: dict[int, list[int]] = {i: [i] for i in range(n)}

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for _, a, b, name in candidates:
        ra, rb = find(a), find(b)
        if ra == rb or name not in class_diameters_m:
            continue
        union = members[ra] + members[rb]
        idx = np.concatenate([groups[i] for i in union])
        if extent(points_env[idx]) > size_margin * float(class_diameters_m[name]):
            continue
        parent[rb] = ra
        members[ra] = sorted(union)
        del members[rb]
    return [members[r] for r in sorted(members)]


def _covered(
    points: FloatArray, group: FloatArray, radius_xy: float, rise_m: float
) -> NDArray[np.bool_]:
    """Mask (N,) of (N, 3) ``points`` with a point of (M, 3) ``group`` above them in the
    square column ``|Δx|, |Δy| ≤ radius_xy``, ``radius_xy ≤ Δz ≤ rise_m`` (metres, +z up;
    ``0 < radius_xy < rise_m``): at least as high as the column is wide, so that a noisy
    horizontal sheet does not cover itself."""
    if len(points) == 0 or len(group) == 0:
        return np.zeros(len(points), dtype=bool)
    # the column is the Chebyshev ball of radius radius_xy around its middle once z is
    # scaled by radius_xy / half its height
    half = 0.5 * (rise_m - radius_xy)
    scale = np.array([1.0, 1.0, radius_xy / half])
    lift = np.array([0.0, 0.0, radius_xy + half])
    dist, _ = cKDTree(group * scale).query((points + lift) * scale, 1, p=np.inf)
    return np.asarray(dist < radius_xy)


def walls(
    groups: Sequence[IntArray], points_env: ArrayLike, radius_xy: float, rise_m: float
) -> list[IntArray]:
    """The points of each group of indices into (N, 3) ``points_env`` that have a point of
    their group above them (square column ``|Δx|, |Δy| ≤ radius_xy``,
    ``radius_xy ≤ Δz ≤ rise_m``, metres, +z up): an object's walls, without its top faces
    and without the smear that slopes out from its foot. Raises ComparisonError unless
    ``0 < radius_xy < rise_m``."""
    pts = as_points(points_env, "points_env")
    if not (radius_xy > 0 and rise_m > radius_xy):
        raise ComparisonError(f"walls need 0 < radius_xy < rise_m, got {radius_xy}, {rise_m}")
    return [np.sort(g[_covered(pts[g], pts[g], radius_xy, rise_m)]) for g in groups]


def grow_bases(
    groups: Sequence[IntArray],
    points_env: ArrayLike,
    radius_xy: float,
    band_m: float,
    anchors: Sequence[IntArray] | None = None,
) -> list[IntArray]:
    """Each group of indices into (N, 3) ``points_env`` with the points beneath it added.

    A point outside every group joins a group when one of the group's anchors (its points
    in ``anchors[k]``, by default all of them) lies above it within the square column
    ``|Δx|, |Δy| ≤ radius_xy`` and ``0 < Δz ≤ band_m`` (metres, +z up); a point beneath
    several groups joins the one whose anchor is nearest (Chebyshev distance with Δz scaled
    by radius_xy / band_m, among its 8 nearest anchors). Returns the grown groups (sorted
    indices; each a superset of its input). Raises ComparisonError for a non-positive
    radius or band, or anchors not given for every group.
    """
    pts = as_points(points_env, "points_env")
    if not radius_xy > 0 or not band_m > 0:
        raise ComparisonError(
            f"base growth needs radius_xy > 0 and band_m > 0, got {radius_xy}, {band_m}"
        )
    if anchors is not None and len(anchors) != len(groups):
        raise ComparisonError(f"{len(groups)} groups but {len(anchors)} anchor sets")
    if not groups:
        return []
    others = np.ones(len(pts), dtype=bool)
    others[np.concatenate(groups).astype(np.int64)] = False
    hang = groups if anchors is None else anchors
    members = np.concatenate(hang).astype(np.int64)
    if members.size == 0:
        return [np.sort(g) for g in groups]
    owner = np.repeat(np.arange(len(hang)), [len(g) for g in hang])
    cand = np.flatnonzero(others)
    # cheap superset first: points in a voxel next to a member's voxel (side: the band)
    cand = cand[_near_voxels(pts[cand], pts[members], max(band_m, radius_xy))]
    if cand.size == 0:
        return [np.sort(g) for g in groups]
    # z scaled by radius_xy / band_m: the column is the upper half of the Chebyshev ball of
    # radius radius_xy around the candidate; of its k nearest members, the nearest above it
    scale = np.array([1.0, 1.0, radius_xy / band_m])
    tree = cKDTree(pts[members] * scale)
    n_near = min(8, members.size)
    _, near = tree.query(pts[cand] * scale, n_near, p=np.inf, distance_upper_bound=radius_xy)
    near = near.reshape(len(cand), n_near)
    member_z = np.append(pts[members, 2], -np.inf)  # index members.size: "none found"
    above = member_z[np.minimum(near, members.size)] > pts[cand, 2][:, None]
    hit = above.any(axis=1)
    first = np.argmax(above, axis=1)
    nearest = near[np.arange(len(cand)), first]
    label = owner[nearest[hit]]
    added = cand[hit]
    return [
        np.sort(np.concatenate([g, added[label == k]])).astype(np.int64)
        for k, g in enumerate(groups)
    ]


def prune_skirts(
    grown: Sequence[IntArray],
    seeds: Sequence[IntArray],
    points_env: ArrayLike,
    radius_xy: float,
    rise_m: float,
    width_m: float,
) -> list[IntArray]:
    """Each grown group of indices into (N, 3) ``points_env`` without its skirt.

    A skirt point is a grown point (in ``grown[k]`` but not ``seeds[k]``) that has no
    point of its group above it (square column ``|Δx|, |Δy| ≤ radius_xy``,
    ``radius_xy ≤ Δz ≤ rise_m``: at least as high as the column is wide, so the skirt's own
    noisy points do not cover each other) and lies within ``width_m`` horizontally of a
    seed point: the ring of floor that stereo smears around an object's foot. A low part
    that reaches further out (an L-bracket's foot) keeps all but its first ``width_m``.
    Metres, +z up. Raises ComparisonError for non-positive lengths, ``rise_m`` ≤
    ``radius_xy`` or mismatched lists.
    """
    pts = as_points(points_env, "points_env")
    if not (radius_xy > 0 and rise_m > 0 and width_m > 0):
        raise ComparisonError(
            f"skirt pruning needs positive lengths, got {radius_xy}, {rise_m}, {width_m}"
        )
    if len(grown) != len(seeds):
        raise ComparisonError(f"{len(grown)} grown groups but {len(seeds)} seed groups")
    if not rise_m > radius_xy:
        raise ComparisonError(f"skirt rise {rise_m} m must exceed the column radius {radius_xy} m")
    out = []
    for g, s in zip(grown, seeds, strict=True):
        extra = np.setdiff1d(g, s)
        if extra.size == 0 or s.size == 0:
            out.append(np.sort(g))
            continue
        near_seed = cKDTree(pts[s, :2]).query(pts[extra, :2], distance_upper_bound=width_m)[0]
        cand = extra[np.isfinite(near_seed)]
        if cand.size:
            drop = cand[~_covered(pts[cand], pts[g], radius_xy, rise_m)]
            g = np.setdiff1d(g, drop)
        out.append(np.sort(g).astype(np.int64))
    return out
