"""The comparison job keeps its change clusters' points for the console
(workers.comparison.clusters_npz → app.core.change_clusters)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from app.core import change_clusters
from app.core.storage import LocalStorage
from workers import comparison
from workers.pipeline.compare.options import CompareOptions
from workers.pipeline.compare.results import Change, ClusterResult, CompareResult


def cluster(cluster_id: int, side: str, points: np.ndarray) -> ClusterResult:
    return ClusterResult(
        id=cluster_id,
        side=side,  # type: ignore[arg-type]
        indices=np.arange(len(points)),
        points_env=points,
        boxes={},
        occurrences=0,
        overlaps={},
        mean_iou={},
        metrics={},
        object_name=None,
    )


def test_every_cluster_is_kept_with_its_change_and_at_most_20000_points(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    now = cluster(4, "added", rng.normal(size=(25_000, 3)))
    before = cluster(5, "removed", rng.normal(size=(300, 3)))
    stray = cluster(6, "added", rng.normal(size=(12, 3)))
    moved = Change("m-1", "moved", "drill", "i-1", now, previous_cluster=before)
    result = CompareResult(
        options=CompareOptions(),
        distances={},
        clusters=(now, before, stray),
        changes=(moved,),
        added_distances_m=np.zeros(0),
        removed_distances_m=np.zeros(0),
    )
    storage = LocalStorage(tmp_path)
    key = change_clusters.clusters_key("snapshots/s-2", "c-1", "j-1", 2)
    storage.write_bytes(key, comparison.clusters_npz(result))
    assert key == "snapshots/s-2/comparisons/c-1/j-1-2/clusters.npz"
    stored = {c.id: c for c in change_clusters.read(storage, key) or []}
    assert set(stored) == {4, 5, 6}
    assert (stored[4].side, stored[4].change_id, stored[4].n_points) == ("added", "m-1", 25_000)
    assert (stored[5].side, stored[5].change_id, stored[5].n_points) == ("removed", "m-1", 300)
    assert stored[6].change_id is None
    assert stored[4].points_env.shape == (20_000, 3)
    np.testing.assert_array_equal(stored[5].points_env, before.points_env.astype(np.float32))
    # the file stays small: 20 300 + 12 points of float32, compressed
    assert storage.path(key).stat().st_size < 20_312 * 12 * 1.1


def test_a_photo_missing_from_storage_is_left_out_not_fatal(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """The seen checks read the capture's stored photos; one that is gone leaves its camera
    to depth alone, with a warning, instead of failing the comparison."""
    storage = LocalStorage(tmp_path)
    storage.write_bytes("snapshots/s-1/images/a.jpg", b"jpeg")
    keys = {"a.jpg": "snapshots/s-1/images/a.jpg", "b.jpg": "snapshots/s-1/images/b.jpg"}
    with caplog.at_level(logging.WARNING, logger="workers.comparison"):
        photos = comparison.local_photos(storage, keys)
    assert list(photos) == ["a.jpg"] and photos["a.jpg"].read_bytes() == b"jpeg"
    assert "b.jpg" in caplog.text
