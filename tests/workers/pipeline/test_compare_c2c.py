"""C2C distances equal a brute-force NumPy oracle (tolerance 1e-6 m: both are exact
Euclidean minima in float64; the only difference is summation order, ~1e-16 m)."""

from __future__ import annotations

import numpy as np
import pytest

from workers.pipeline.compare import c2c, c2c_both_ways
from workers.pipeline.errors import ComparisonError, ShapeError


def brute_force(compared: np.ndarray, reference: np.ndarray) -> np.ndarray:
    out = np.empty(len(compared))
    for s in range(0, len(compared), 512):
        block = compared[s : s + 512]
        d2 = ((block[:, None, :] - reference[None, :, :]) ** 2).sum(axis=2)
        out[s : s + 512] = np.sqrt(d2.min(axis=1))
    return out


def surface_cloud(rng: np.random.Generator, n: int) -> np.ndarray:
    xy = rng.uniform(-1, 1, (n, 2))
    z = 0.1 * np.sin(3 * xy[:, 0]) + rng.normal(0, 0.002, n)
    return np.column_stack([xy, z])


def test_c2c_equals_brute_force_both_ways() -> None:
    rng = np.random.default_rng(0)
    before = surface_cloud(rng, 3000)
    after = np.concatenate([surface_cloud(rng, 2500), rng.uniform(-0.2, 0.2, (300, 3)) + 0.5])
    after = np.concatenate([after, before[:50]])  # exact duplicates: distance 0
    res = c2c_both_ways(before, after)
    np.testing.assert_allclose(res.added, brute_force(after, before), atol=1e-6, rtol=0)
    np.testing.assert_allclose(res.removed, brute_force(before, after), atol=1e-6, rtol=0)
    assert np.all(res.added[-50:] == 0.0)
    assert res.added.shape == (len(after),) and res.removed.shape == (len(before),)


def test_c2c_uniform_volume_and_single_point() -> None:
    rng = np.random.default_rng(1)
    a, b = rng.normal(size=(1000, 3)), rng.normal(size=(700, 3)) * 2
    np.testing.assert_allclose(c2c(a, b), brute_force(a, b), atol=1e-6, rtol=0)
    one = np.array([[0.0, 0.0, 0.0]])
    np.testing.assert_allclose(c2c(a, one), np.linalg.norm(a, axis=1), atol=1e-12)


def test_c2c_rejects_bad_input() -> None:
    with pytest.raises(ShapeError):
        c2c(np.zeros((5, 2)), np.zeros((5, 3)))
    with pytest.raises(ComparisonError):
        c2c(np.zeros((0, 3)), np.zeros((5, 3)))
