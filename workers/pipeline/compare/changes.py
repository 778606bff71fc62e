"""Change types against the twin: added, removed, moved, swapped (and unidentified).

Order of decisions (all pairings are optimal assignments, Hungarian, on centroid distance):
1. each identified *removed* cluster closes the nearest twin instance of its class within
   ``max(instance_match_min, instance_match_factor × diameter)`` metres;
2. *moved*: a removed and an added cluster of the same class, ≤ ``moved_max_distance`` apart;
   the instance keeps its id;
3. *swapped*: a leftover removed and a leftover added cluster of different classes whose
   centroids are < ``swap_distance_factor × max(diameters)`` apart (about the same place);
4. leftovers: *added* (a new instance id) and *removed*;
   (an identified cluster the other capture's detector still names at its place is
   left out of steps 3 and 4: a hole in one reconstruction, not a change);
5. unidentified clusters of at least ``unidentified_min_points`` points found at the strict
   threshold (growth does not count) are reported as ``unidentified`` changes; they all
   stay in the clusters table.
Clusters the caller found no evidence of a change for (``not_changes``: a hole in the other
cloud, a piece of an object standing in both captures) take part in none of the steps.
Identity across snapshots: moved keeps the closed instance's id; added and swapped-in
objects get a new one from ``new_id``.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

from workers.pipeline.compare.data import TwinInstance
from workers.pipeline.compare.options import CompareOptions
from workers.pipeline.compare.results import Change, ClusterResult

FloatArray = NDArray[np.float64]


def _assign(cost: FloatArray, limit: FloatArray) -> list[tuple[int, int]]:
    """Optimal pairs (row, col) of a (R, C) cost matrix, keeping only cost ≤ limit (R, C)."""
    if cost.size == 0:
        return []
    ok = cost <= limit
    if not np.any(ok):
        return []
    big = float(np.max(cost[ok])) * 10.0 + 1e6
    rows, cols = linear_sum_assignment(np.where(ok, cost, big))
    return [(int(r), int(c)) for r, c in zip(rows, cols, strict=True) if ok[r, c]]


def _dist(a: Sequence[FloatArray], b: Sequence[FloatArray]) -> FloatArray:
    if not a or not b:
        return np.zeros((len(a), len(b)))
    return np.asarray(np.linalg.norm(np.asarray(a)[:, None, :] - np.asarray(b)[None, :, :], axis=2))


@dataclass(frozen=True)
class _Identified:
    """The identified clusters of each side and, for removed cluster i, the twin instance
    it closes (``closes[i]``, absent when none of its class is near enough)."""

    added: list[ClusterResult]
    removed: list[ClusterResult]
    closes: dict[int, TwinInstance]


@dataclass(frozen=True)
class _Paired:
    """Changes made from pairs, and the indices into ``_Identified.removed`` / ``.added``
    of the clusters they used."""

    changes: list[Change]
    removed_used: frozenset[int]
    added_used: frozenset[int]


def _diameter(class_diameters_m: Mapping[str, float], name: str | None) -> float:
    return float(class_diameters_m.get(name or "", 0.0))


def _close_instances(
    removed: Sequence[ClusterResult],
    twin: Sequence[TwinInstance],
    class_diameters_m: Mapping[str, float],
    options: CompareOptions,
) -> dict[int, TwinInstance]:
    """Step 1: each removed cluster → the nearest twin instance of its class within
    ``max(instance_match_min, instance_match_factor × diameter)`` metres."""
    closes: dict[int, TwinInstance] = {}
    for name in sorted({c.object_name for c in removed if c.object_name}):
        rs = [i for i, c in enumerate(removed) if c.object_name == name]
        ts = [t for t in twin if t.object_name == name]
        cost = _dist([removed[i].centroid for i in rs], [t.centroid for t in ts])
        diameter = _diameter(class_diameters_m, name)
        lim = max(options.instance_match_min, options.instance_match_factor * diameter)
        for r, t in _assign(cost, np.full(cost.shape, lim)):
            closes[rs[r]] = ts[t]
    return closes


def _moved(found: _Identified, options: CompareOptions, new_id: Callable[[], str]) -> _Paired:
    """Step 2: a removed and an added cluster of one class ≤ ``moved_max_distance`` apart;
    the instance keeps its id."""
    added, removed = found.added, found.removed
    changes: list[Change] = []
    used_r: set[int] = set()
    used_a: set[int] = set()
    for name in sorted({c.object_name for c in added if c.object_name}):
        rs = [i for i, c in enumerate(removed) if c.object_name == name]
        as_ = [i for i, c in enumerate(added) if c.object_name == name]
        cost = _dist([removed[i].centroid for i in rs], [added[i].centroid for i in as_])
        for r, a in _assign(cost, np.full(cost.shape, options.moved_max_distance)):
            ri, ai = rs[r], as_[a]
            used_r.add(ri)
            used_a.add(ai)
            inst = found.closes.get(ri)
            changes.append(
                Change(
                    id=new_id(),
                    type="moved",
                    object_name=name,
                    instance_id=inst.instance_id if inst else new_id(),
                    cluster=added[ai],
                    previous_cluster=removed[ri],
                    previous_env_from_object=inst.env_from_object if inst else None,
                )
            )
    return _Paired(changes, frozenset(used_r), frozenset(used_a))


def _swapped(
    found: _Identified,
    moved: _Paired,
    class_diameters_m: Mapping[str, float],
    options: CompareOptions,
    new_id: Callable[[], str],
) -> _Paired:
    """Step 3: a leftover removed and a leftover added cluster of different classes whose
    centroids are < ``swap_distance_factor × max(diameters)`` apart."""
    added, removed = found.added, found.removed
    rs = [i for i in range(len(removed)) if i not in moved.removed_used]
    as_ = [i for i in range(len(added)) if i not in moved.added_used]
    cost = _dist([removed[i].centroid for i in rs], [added[i].centroid for i in as_])
    limit = np.array(
        [
            [
                options.swap_distance_factor
                * max(
                    _diameter(class_diameters_m, removed[r].object_name),
                    _diameter(class_diameters_m, added[a].object_name),
                )
                if removed[r].object_name != added[a].object_name
                else -1.0
                for a in as_
            ]
            for r in rs
        ]
    ).reshape(len(rs), len(as_))
    changes: list[Change] = []
    used_r: set[int] = set()
    used_a: set[int] = set()
    for r, a in _assign(cost, limit):
        ri, ai = rs[r], as_[a]
        used_r.add(ri)
        used_a.add(ai)
        inst = found.closes.get(ri)
        changes.append(
            Change(
                id=new_id(),
                type="swapped",
                object_name=added[ai].object_name,
                instance_id=new_id(),
                cluster=added[ai],
                previous_cluster=removed[ri],
                previous_env_from_object=inst.env_from_object if inst else None,
                replaced_object=removed[ri].object_name,
                replaced_instance_id=inst.instance_id if inst else None,
            )
        )
    return _Paired(changes, frozenset(used_r), frozenset(used_a))


def _leftovers(
    found: _Identified, used_r: Collection[int], used_a: Collection[int], new_id: Callable[[], str]
) -> list[Change]:
    """Step 4: the unpaired removed clusters (closing their instance), then the unpaired
    added ones (a new instance id)."""
    changes: list[Change] = []
    for ri, c in enumerate(found.removed):
        if ri in used_r:
            continue
        inst = found.closes.get(ri)
        changes.append(
            Change(
                id=new_id(),
                type="removed",
                object_name=c.object_name,
                instance_id=inst.instance_id if inst else None,
                cluster=c,
                previous_env_from_object=inst.env_from_object if inst else None,
            )
        )
    for ai, c in enumerate(found.added):
        if ai in used_a:
            continue
        changes.append(
            Change(
                id=new_id(),
                type="added",
                object_name=c.object_name,
                instance_id=new_id(),
                cluster=c,
            )
        )
    return changes


def _unidentified(
    clusters: Sequence[ClusterResult],
    options: CompareOptions,
    not_changes: Collection[int],
    new_id: Callable[[], str],
) -> list[Change]:
    """Step 5: unidentified clusters are reported, never dropped, once they are large
    enough to be an object (identified clusters have the detector's evidence; an
    unidentified speck is noise)."""
    return [
        Change(id=new_id(), type="unidentified", object_name=None, instance_id=None, cluster=c)
        for c in clusters
        if (
            c.object_name is None
            and c.n_evidence_points >= options.unidentified_min_points
            and c.id not in not_changes
        )
    ]


def classify_changes(
    clusters: Sequence[ClusterResult],
    twin: Sequence[TwinInstance],
    class_diameters_m: Mapping[str, float],
    options: CompareOptions,
    new_id: Callable[[], str],
    not_changes: Collection[int] = (),
    still_there: Collection[int] = (),
) -> list[Change]:
    """Changes from identified clusters and the twin state (see module docstring).
    ``not_changes``: ids of clusters without evidence of a change (kept in the clusters
    table, neither paired nor reported); ``still_there``: ids of identified clusters the
    other capture's detector still names at their place: they may pair as a move, but
    are neither swapped nor reported alone."""
    named = [c for c in clusters if c.object_name is not None and c.id not in not_changes]
    added = [c for c in named if c.side == "added"]
    removed = [c for c in named if c.side == "removed"]
    closes = _close_instances(removed, twin, class_diameters_m, options)
    found = _Identified(added=added, removed=removed, closes=closes)
    moved = _moved(found, options, new_id)
    # the still-there clusters count as used from here on: no swap, no leftover
    held_r = {i for i, c in enumerate(removed) if c.id in still_there}
    held_a = {i for i, c in enumerate(added) if c.id in still_there}
    moved = _Paired(moved.changes, moved.removed_used | held_r, moved.added_used | held_a)
    swapped = _swapped(found, moved, class_diameters_m, options, new_id)
    used_r = moved.removed_used | swapped.removed_used
    used_a = moved.added_used | swapped.added_used
    return [
        *moved.changes,
        *swapped.changes,
        *_leftovers(found, used_r, used_a, new_id),
        *_unidentified(clusters, options, not_changes, new_id),
    ]
