"""Change types against the twin: added, removed, moved, swapped (and unidentified).

Order of decisions (all pairings are optimal assignments, Hungarian, on centroid distance):
1. each identified *removed* cluster closes the nearest twin instance of its class within
   ``max(instance_match_min, instance_match_factor × diameter)`` metres;
2. *moved*: a removed and an added cluster of the same class, ≤ ``moved_max_distance`` apart;
   the instance keeps its id;
3. *swapped*: a leftover removed and a leftover added cluster of different classes whose
   centroids are < ``swap_distance_factor × max(diameters)`` apart (about the same place);
4. leftovers: *added* (a new instance id) and *removed*;
5. unidentified clusters of at least ``unidentified_min_points`` points found at the strict
   threshold (growth does not count) are reported as ``unidentified`` changes, never
   dropped; they all stay in the clusters table.
Identity across snapshots: moved keeps the closed instance's id; added and swapped-in
objects get a new one from ``new_id``.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Mapping, Sequence

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


def classify_changes(
    clusters: Sequence[ClusterResult],
    twin: Sequence[TwinInstance],
    class_diameters_m: Mapping[str, float],
    options: CompareOptions,
    new_id: Callable[[], str],
    not_changes: Collection[int] = (),
) -> list[Change]:
    """Changes from identified clusters and the twin state (see module docstring).
    ``not_changes``: ids of unidentified clusters without evidence of a change (kept in
    the clusters table, not reported)."""

    def diameter(name: str | None) -> float:
        return float(class_diameters_m.get(name or "", 0.0))

    added = [c for c in clusters if c.side == "added" and c.object_name is not None]
    removed = [c for c in clusters if c.side == "removed" and c.object_name is not None]

    # 1. removed cluster -> twin instance of its class
    closes: dict[int, TwinInstance] = {}
    for name in sorted({c.object_name for c in removed if c.object_name}):
        rs = [i for i, c in enumerate(removed) if c.object_name == name]
        ts = [t for t in twin if t.object_name == name]
        cost = _dist([removed[i].centroid for i in rs], [t.centroid for t in ts])
        lim = max(options.instance_match_min, options.instance_match_factor * diameter(name))
        for r, t in _assign(cost, np.full(cost.shape, lim)):
            closes[rs[r]] = ts[t]

    changes: list[Change] = []
    used_r: set[int] = set()
    used_a: set[int] = set()

    # 2. moved: same class
    for name in sorted({c.object_name for c in added if c.object_name}):
        rs = [i for i, c in enumerate(removed) if c.object_name == name]
        as_ = [i for i, c in enumerate(added) if c.object_name == name]
        cost = _dist([removed[i].centroid for i in rs], [added[i].centroid for i in as_])
        for r, a in _assign(cost, np.full(cost.shape, options.moved_max_distance)):
            ri, ai = rs[r], as_[a]
            used_r.add(ri)
            used_a.add(ai)
            inst = closes.get(ri)
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

    # 3. swapped: different classes at about the same place
    rs = [i for i in range(len(removed)) if i not in used_r]
    as_ = [i for i in range(len(added)) if i not in used_a]
    cost = _dist([removed[i].centroid for i in rs], [added[i].centroid for i in as_])
    limit = np.array(
        [
            [
                options.swap_distance_factor
                * max(diameter(removed[r].object_name), diameter(added[a].object_name))
                if removed[r].object_name != added[a].object_name
                else -1.0
                for a in as_
            ]
            for r in rs
        ]
    ).reshape(len(rs), len(as_))
    for r, a in _assign(cost, limit):
        ri, ai = rs[r], as_[a]
        used_r.add(ri)
        used_a.add(ai)
        inst = closes.get(ri)
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

    # 4. leftovers
    for ri, c in enumerate(removed):
        if ri in used_r:
            continue
        inst = closes.get(ri)
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
    for ai, c in enumerate(added):
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

    # 5. unidentified: reported, never dropped, once they are large enough to be an object
    # (identified clusters have the detector's evidence; an unidentified speck is noise)
    for c in clusters:
        if (
            c.object_name is None
            and c.n_evidence_points >= options.unidentified_min_points
            and c.id not in not_changes
        ):
            changes.append(
                Change(
                    id=new_id(), type="unidentified", object_name=None, instance_id=None, cluster=c
                )
            )
    return changes
