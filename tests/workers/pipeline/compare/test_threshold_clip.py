"""A clipped mean + k·σ threshold: one large change (a column, a tenth of the points) cannot
lift it above a smaller change, and without such a tail it stays near the plain one."""

from __future__ import annotations

import numpy as np
import pytest

from workers.pipeline.compare import ThresholdSpec, distance_stats
from workers.pipeline.compare.thresholds import clipped
from workers.pipeline.errors import InputError


def _surface(n: int, seed: int) -> np.ndarray:
    """Unchanged surface: half-normal distances, σ 1.5 mm."""
    return np.abs(np.random.default_rng(seed).normal(0.0, 0.0015, n))


def test_a_large_change_does_not_lift_the_clipped_threshold() -> None:
    surface = _surface(90_000, 1)
    box = np.random.default_rng(2).uniform(0.05, 0.23, 2_000)  # a 23 cm box
    column = np.random.default_rng(3).uniform(0.2, 1.2, 10_000)  # a 1.2 m column
    d = np.concatenate([surface, box, column])
    plain = distance_stats(d, ThresholdSpec(kind="mean_std", k=1.0)).threshold
    clip = distance_stats(d, ThresholdSpec(kind="mean_std", k=1.0, clip=6.0)).threshold
    assert plain > 0.2  # above most of the box
    assert clip < 0.006 and np.mean(box > clip) == 1.0
    # the reported statistics stay those of every distance
    stats = distance_stats(d, ThresholdSpec(kind="mean_std", k=1.0, clip=6.0))
    assert stats.mean == pytest.approx(float(d.mean()))


def test_clipping_an_unchanged_surface_changes_little() -> None:
    d = _surface(50_000, 4)
    plain = distance_stats(d, ThresholdSpec(kind="mean_std", k=1.0)).threshold
    clip = distance_stats(d, ThresholdSpec(kind="mean_std", k=1.0, clip=6.0)).threshold
    assert clip == pytest.approx(plain, rel=0.02)


def test_clipped_keeps_the_bulk_and_is_never_empty() -> None:
    d = np.array([0.001, 0.001, 0.002, 0.002, 0.003, 1.0])
    assert clipped(d, 3.0).max() == 0.003
    same = np.full(4, 0.002)  # MAD 0: everything at the median is kept
    np.testing.assert_array_equal(clipped(same, 3.0), same)


def test_clip_round_trips_and_is_checked() -> None:
    spec = ThresholdSpec.from_json({"kind": "mean_std", "k": 1.0, "clip": 6.0})
    assert spec.to_json() == {"kind": "mean_std", "k": 1.0, "clip": 6.0}
    assert ThresholdSpec(kind="mean_std").to_json() == {"kind": "mean_std", "k": 1.0}
    with pytest.raises(InputError, match="clip"):
        ThresholdSpec(kind="mean_std", clip=0.0)
