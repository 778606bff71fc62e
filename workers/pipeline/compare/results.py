"""Typed results of the compare stage and their contract JSON (docs/contract.md "A comparison")."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from workers.pipeline.compare.options import CompareOptions
from workers.pipeline.compare.thresholds import DistanceStats

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
Side = Literal["added", "removed"]
ChangeType = Literal["added", "removed", "moved", "swapped", "unidentified"]


@dataclass(frozen=True, eq=False)
class ClusterResult:
    """One (possibly merged) cluster of changed points.

    ``side``: "added" (points of the *after* cloud) or "removed" (of the *before* cloud);
    ``indices`` (n,) into that cloud; ``points_env`` (n, 3) metres, environment frame;
    ``boxes`` image name → (4,) box ``[x1, y1, x2, y2]`` px in that side's capture;
    ``metrics``/``mean_iou``/``overlaps`` per class name; ``object_name`` the identified
    class or None; ``merged_from`` the raw cluster numbers it was built from;
    ``n_seed_points`` how many of its points were found at the strict threshold, before
    hysteresis growth (None: not grown).
    """

    id: int
    side: Side
    indices: IntArray
    points_env: FloatArray
    boxes: dict[str, FloatArray]
    occurrences: int
    overlaps: dict[str, int]
    mean_iou: dict[str, float]
    metrics: dict[str, float]
    object_name: str | None
    merged_from: tuple[int, ...] = ()
    n_seed_points: int | None = None

    @property
    def n_points(self) -> int:
        return len(self.indices)

    @property
    def n_evidence_points(self) -> int:
        """Points found at the strict threshold (all of them when the cluster was not grown)."""
        return self.n_points if self.n_seed_points is None else self.n_seed_points

    @property
    def centroid(self) -> FloatArray:
        """(3,) mean of the cluster's points, metres."""
        return np.asarray(self.points_env.mean(axis=0), dtype=np.float64)

    @property
    def bbox_min(self) -> FloatArray:
        return np.asarray(self.points_env.min(axis=0), dtype=np.float64)

    @property
    def bbox_max(self) -> FloatArray:
        return np.asarray(self.points_env.max(axis=0), dtype=np.float64)

    def summary_json(self) -> dict[str, Any]:
        """The ``cluster`` object of a change."""
        return {
            "id": self.id,
            "side": self.side,
            "n_points": self.n_points,
            "centroid": self.centroid.tolist(),
            "bbox_min": self.bbox_min.tolist(),
            "bbox_max": self.bbox_max.tolist(),
        }

    def identification_json(self, name: str | None = None) -> dict[str, Any]:
        """``{"metric", "iou", "overlaps", "occurrences"}`` for class ``name`` (default: the
        identified class, else the best-scoring one; adds ``"object"``)."""
        if name is None:
            name = self.object_name
        if name is None and self.metrics:
            name = max(self.metrics, key=lambda k: self.metrics[k])
        if name is None:
            return {
                "object": None,
                "metric": 0.0,
                "iou": 0.0,
                "overlaps": 0,
                "occurrences": self.occurrences,
            }
        return {
            "object": name,
            "metric": self.metrics.get(name, 0.0),
            "iou": self.mean_iou.get(name, 0.0),
            "overlaps": self.overlaps.get(name, 0),
            "occurrences": self.occurrences,
        }

    def table_json(self) -> dict[str, Any]:
        """A row of the comparison's ``clusters`` table."""
        return {
            **self.summary_json(),
            "object": self.object_name,
            "occurrences": self.occurrences,
            "metrics": dict(self.metrics),
            "merged_from": list(self.merged_from),
            "n_seed_points": self.n_seed_points,
        }


@dataclass(frozen=True, eq=False)
class Change:
    """One change to the twin. Pose fields are left None for the pose step.

    ``cluster`` is the evidence where the object is now (added/moved/swapped) or was
    (removed/unidentified-removed); ``previous_cluster`` the removed cluster of a moved or
    swapped pair; ``previous_env_from_object`` (4, 4) the closed instance's pose
    (removed, moved, and the replaced instance of swapped) when the twin had it.
    """

    id: str
    type: ChangeType
    object_name: str | None
    instance_id: str | None
    cluster: ClusterResult
    previous_cluster: ClusterResult | None = None
    previous_env_from_object: FloatArray | None = None
    replaced_object: str | None = None
    replaced_instance_id: str | None = None
    env_from_object: FloatArray | None = None
    pose_quality: dict[str, Any] | None = None

    def to_json(self) -> dict[str, Any]:
        """The contract's change object (extended with ``previous_cluster``,
        ``replaced_instance_id``; ``side`` for unidentified changes)."""
        out: dict[str, Any] = {
            "id": self.id,
            "type": self.type,
            "object": self.object_name,
            "instance_id": self.instance_id,
            "pose": None if self.env_from_object is None else self.env_from_object.tolist(),
            "previous_pose": (
                None
                if self.previous_env_from_object is None
                else self.previous_env_from_object.tolist()
            ),
            "identification": self.cluster.identification_json(self.object_name),
            "cluster": self.cluster.summary_json(),
            "pose_quality": self.pose_quality,
        }
        if self.type == "swapped":
            out["replaced_object"] = self.replaced_object
            out["replaced_instance_id"] = self.replaced_instance_id
        if self.previous_cluster is not None:
            out["previous_cluster"] = self.previous_cluster.summary_json()
        if self.type == "unidentified":
            out["side"] = self.cluster.side
        return out


@dataclass(frozen=True, eq=False)
class CompareResult:
    """Everything the compare stage found. ``distances`` per side ("added", "removed");
    ``added_distances_m`` (N_after,) and ``removed_distances_m`` (N_before,) the raw C2C
    distances; ``stats`` counts and timings (seconds)."""

    options: CompareOptions
    distances: dict[str, DistanceStats]
    clusters: tuple[ClusterResult, ...]
    changes: tuple[Change, ...]
    added_distances_m: FloatArray
    removed_distances_m: FloatArray
    stats: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        """The comparison JSON of docs/contract.md, less ``id``/``before``/``after``/``job``
        (the service adds those)."""
        return {
            "options": self.options.to_json(),
            "distances": {side: s.to_json() for side, s in self.distances.items()},
            "changes": [c.to_json() for c in self.changes],
            "clusters": [c.table_json() for c in self.clusters],
            "stats": dict(self.stats),
        }
