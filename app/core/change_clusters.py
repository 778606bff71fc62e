"""A comparison's change clusters as points: the artifact the comparison job writes and the
console draws (``GET /v1/comparisons/{id}/clusters``) and re-projects into photos
(``.../changes/{change_id}/views``).

One ``clusters.npz`` per comparison, beside the *after* snapshot's files, in the folder of
the job attempt that made it (``<after prefix>/comparisons/<comparison id>/<job id>-<attempt>
/clusters.npz``: a stale attempt never overwrites the winner's, whose attempt the job row
keeps; directly in the comparison's folder for one made before), so it goes with that
snapshot's files. Arrays (NumPy ``.npz``, no pickled objects):

- ``ids`` (C,) int64: the cluster ids of the comparison's ``clusters`` table;
- ``sides`` (C,) str: ``added`` (points of the after cloud) or ``removed`` (of the before);
- ``change_ids`` (C,) str: the change whose evidence the cluster is ('' for none; a moved or
  swapped change names both its clusters);
- ``n_points`` (C,) int64: the cluster's points in full;
- ``offsets`` (C + 1,) int64 and ``points_env`` (P, 3) float32: cluster c's stored points are
  ``points_env[offsets[c]:offsets[c + 1]]``, environment frame, metres: all of them, or
  :data:`MAX_STORED_POINTS` drawn with a fixed seed when it has more.
"""

from __future__ import annotations

import io
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from app.core.errors import Conflict
from app.core.jobs import attempt_folder
from app.core.storage import Storage

MAX_STORED_POINTS = 20_000
SEED = 0


@dataclass(frozen=True)
class StoredCluster:
    """One cluster: its ``id``, ``side``, ``change_id`` (None: no change), ``n_points`` in
    full and ``points_env`` (n, 3) float32 metres (at most :data:`MAX_STORED_POINTS`)."""

    id: int
    side: str
    change_id: str | None
    n_points: int
    points_env: NDArray[np.floating]


def comparison_folder(after_storage_prefix: str, comparison_id: str) -> str:
    """The storage key of the folder holding a comparison's artifacts (one per comparison:
    a re-run is a new comparison, a retry rewrites its own); deleting a comparison deletes it."""
    return f"{after_storage_prefix}/comparisons/{comparison_id}"


FILE = "clusters.npz"


def clusters_key(
    after_storage_prefix: str, comparison_id: str, job_id: str | None = None, attempt: int = 0
) -> str:
    """The storage key of a comparison's cluster points as attempt ``attempt`` of its job
    ``job_id`` publishes them; without ``job_id``, where comparisons made before attempts
    had folders keep them."""
    folder = comparison_folder(after_storage_prefix, comparison_id)
    if job_id is not None:
        folder = attempt_folder(folder, job_id, attempt)
    return f"{folder}/{FILE}"


def subsample(
    points_env: NDArray[np.floating], limit: int = MAX_STORED_POINTS
) -> NDArray[np.float32]:
    """(≤ limit, 3) float32: ``points_env`` (n, 3) whole, or ``limit`` of them drawn with a
    fixed seed (in their order)."""
    pts = np.asarray(points_env, dtype=np.float32).reshape(-1, 3)
    if len(pts) <= limit:
        return pts
    keep = np.sort(np.random.default_rng(SEED).choice(len(pts), limit, replace=False))
    return pts[keep]


def to_npz(clusters: Sequence[StoredCluster]) -> bytes:
    """The ``clusters.npz`` bytes of ``clusters`` (points subsampled to the limit)."""
    points = [subsample(c.points_env) for c in clusters]
    offsets = np.concatenate([[0], np.cumsum([len(p) for p in points])]).astype(np.int64)
    buf = io.BytesIO()
    np.savez_compressed(
        buf,
        ids=np.array([c.id for c in clusters], dtype=np.int64),
        sides=np.array([c.side for c in clusters], dtype=np.str_),
        change_ids=np.array([c.change_id or "" for c in clusters], dtype=np.str_),
        n_points=np.array([c.n_points for c in clusters], dtype=np.int64),
        offsets=offsets,
        points_env=np.concatenate(points) if points else np.zeros((0, 3), np.float32),
    )
    return buf.getvalue()


def write(storage: Storage, key: str, clusters: Sequence[StoredCluster]) -> None:
    """Store ``clusters`` under ``key`` (atomically)."""
    storage.write_bytes(key, to_npz(clusters))


def read(storage: Storage, key: str) -> list[StoredCluster] | None:
    """The clusters stored under ``key``; None when there is no file (a comparison made
    before the artifact existed, or not finished). Conflict (409 ClustersUnreadable) for a
    file that is not one."""
    try:
        path = storage.local_file(key)
    except FileNotFoundError:
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            ids, sides, change_ids = data["ids"], data["sides"], data["change_ids"]
            n_points, offsets, points = data["n_points"], data["offsets"], data["points_env"]
        if len(offsets) != len(ids) + 1 or points.ndim != 2 or points.shape[1] != 3:
            raise ValueError("arrays do not fit together")
    except (OSError, KeyError, ValueError) as exc:
        raise Conflict(
            f"the stored change clusters cannot be read: {exc}", code="ClustersUnreadable"
        ) from exc
    return [
        StoredCluster(
            id=int(ids[c]),
            side=str(sides[c]),
            change_id=str(change_ids[c]) or None,
            n_points=int(n_points[c]),
            points_env=points[offsets[c] : offsets[c + 1]],
        )
        for c in range(len(ids))
    ]
