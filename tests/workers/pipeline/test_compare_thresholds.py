"""Thresholds on known distributions, cloud statistics on known surfaces, options."""

from __future__ import annotations

import numpy as np
import pytest

from workers.pipeline.compare import (
    PRESETS,
    CompareOptions,
    ThresholdSpec,
    distance_stats,
    options_from_json,
)
from workers.pipeline.compare.c2c import build_tree
from workers.pipeline.compare.thresholds import CloudStats, cloud_stats, lod_threshold
from workers.pipeline.errors import ComparisonError, InputError


@pytest.mark.parametrize("k", [0.0, 0.5, 1.0, 1.5])
def test_mean_std_levels_on_half_normal(k: float) -> None:
    # |N(0, σ)|: mean σ·sqrt(2/π), std σ·sqrt(1 − 2/π); 10⁶ samples → relative error < 0.5 %
    sigma = 0.01
    d = np.abs(np.random.default_rng(0).normal(0, sigma, 1_000_000))
    s = distance_stats(d, ThresholdSpec(kind="mean_std", k=k))
    mean, std = sigma * np.sqrt(2 / np.pi), sigma * np.sqrt(1 - 2 / np.pi)
    assert s.mean == pytest.approx(mean, rel=5e-3)
    assert s.std == pytest.approx(std, rel=5e-3)
    assert s.threshold == pytest.approx(mean + k * std, rel=5e-3)
    assert s.threshold == pytest.approx(d.mean() + k * d.std(), rel=1e-12)


def test_fixed_threshold_and_json() -> None:
    s = distance_stats(
        [0.0, 1.0, 2.0], ThresholdSpec.from_json({"kind": "fixed", "distance": 0.02})
    )
    assert (s.mean, s.threshold) == (1.0, 0.02)
    assert s.std == pytest.approx(np.sqrt(2 / 3))
    assert s.to_json() == {
        "mean": 1.0,
        "std": s.std,
        "threshold": 0.02,
        "grow_threshold": None,
        "n": 3,
        "region": "all",
    }
    assert ThresholdSpec(kind="mean_std", k=1.0).to_json() == {"kind": "mean_std", "k": 1.0}
    with pytest.raises(InputError):
        ThresholdSpec.from_json({"kind": "median"})
    with pytest.raises(InputError):
        ThresholdSpec.from_json({"kind": "fixed", "distanse": 0.1})


def test_cloud_stats_on_a_noisy_grid_plane() -> None:
    # grid spacing 1 cm → median NN spacing ≈ 1 cm (noise 1 mm shifts it < 10 %);
    # PCA-plane RMS of k=16 neighbours ≈ σ·sqrt(1 − 3/16) for σ = 2 mm (3 fitted dof)
    g = np.arange(0, 1, 0.01)
    x, y = np.meshgrid(g, g)
    rng = np.random.default_rng(0)
    pts = np.column_stack([x.ravel(), y.ravel(), rng.normal(0, 0.002, x.size)])
    stats = cloud_stats(build_tree(pts), sample=3000, neighbours=16)
    assert stats.spacing == pytest.approx(0.01, rel=0.1)
    assert stats.roughness == pytest.approx(0.002 * np.sqrt(13 / 16), rel=0.15)


def test_lod_formula_and_spec() -> None:
    q, r = CloudStats(spacing=0.005, roughness=0.003), CloudStats(spacing=0.01, roughness=0.004)
    expected = np.sqrt(1.96**2 * (0.003**2 + 0.004**2) + (2 * 0.01) ** 2) + 0.002
    assert lod_threshold(q, r, 0.002) == pytest.approx(expected)
    spec = ThresholdSpec(kind="lod")
    assert distance_stats([0.1], spec, q, r, 0.002).threshold == pytest.approx(expected)
    fixed_reg = ThresholdSpec(kind="lod", registration=0.0)
    assert distance_stats([0.1], fixed_reg, q, r, 0.002).threshold == pytest.approx(
        expected - 0.002
    )
    with pytest.raises(ComparisonError):
        distance_stats([0.1], spec)


def test_presets_and_overrides() -> None:
    assert set(PRESETS) >= {"default", "thesis"}
    assert PRESETS["thesis"].use_visibility is False
    opts = options_from_json("default", {"threshold": {"kind": "fixed", "distance": 0.05}})
    assert opts.threshold == ThresholdSpec(kind="fixed", distance=0.05)
    assert opts.to_json()["threshold"] == {"kind": "fixed", "distance": 0.05}
    assert options_from_json("thesis").to_json() == PRESETS["thesis"].to_json()
    with pytest.raises(InputError):
        options_from_json("nope")
    with pytest.raises(InputError):
        options_from_json("default", {"no_such_option": 1})
    with pytest.raises(InputError):
        CompareOptions(cluster_min_points=0)
    for bad in ({"skirt_width_factor": -1.0}, {"skirt_rise_m": 0.0}, {"skirt_radius_factor": 0.0}):
        with pytest.raises(InputError, match="skirt"):
            options_from_json("default", bad)
