"""Change thresholds over C2C distances, and the clouds' spacing and roughness.

- ``mean_std``: mean + k·std of the side's distances (the thesis's levels k = 0, .5, 1, 1.5).
- ``fixed``: a distance in metres.
- ``lod``: a level of detection adapted from M3C2's
  ``LoD95 = 1.96·sqrt(σ1²/n1 + σ2²/n2) + reg``. C2C compares single points, not means over
  n-point neighbourhoods, so n = 1 per side, and a point-to-point distance has one more term:
  the gap to the nearest sample of a surface sampled at spacing s (the reference's median
  nearest-neighbour distance). Hence, for the compared side q against reference r,
  ``lod = sqrt(z²·(σ_q² + σ_r²) + (f·s_r)²) + reg``, with σ the median local roughness
  (RMS distance to the local PCA plane of k neighbours), z = 1.96, f = 2 (for a
  Poisson-sampled surface the 95 % quantile of the gap to the nearest sample is
  sqrt(ln 20 / ln 2) ≈ 2.08 × the median NN spacing; a grid needs only 0.63×), and reg the
  registration error between the captures (``sqrt(res_b² + res_a²)`` of their alignment
  residuals to the environment frame) unless given.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from workers.pipeline.compare.options import ThresholdSpec
from workers.pipeline.errors import ComparisonError

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class DistanceStats:
    """Mean, standard deviation (population, as CloudCompare) and threshold, metres, over
    ``n`` distances of ``region`` ("all" points or the "overlap" of the two captures)."""

    mean: float
    std: float
    threshold: float
    n: int = 0
    region: str = "all"
    grow_threshold: float | None = None  # hysteresis growth's lower threshold, metres

    def to_json(self) -> dict[str, float | int | str | None]:
        return {
            "mean": self.mean,
            "std": self.std,
            "threshold": self.threshold,
            "grow_threshold": self.grow_threshold,
            "n": self.n,
            "region": self.region,
        }


@dataclass(frozen=True)
class CloudStats:
    """Median nearest-neighbour ``spacing`` and median local ``roughness`` (σ), metres."""

    spacing: float
    roughness: float


def _sample(n: int, size: int, seed: int) -> NDArray[np.int64]:
    if n <= size:
        return np.arange(n, dtype=np.int64)
    return np.sort(np.random.default_rng(seed).choice(n, size=size, replace=False))


def cloud_stats(
    tree: cKDTree,
    sample: int = 20_000,
    neighbours: int = 16,
    seed: int = 0,
    roughness: bool = True,
) -> CloudStats:
    """Spacing and roughness of the cloud in ``tree`` from a seeded sample of its points.

    Spacing: median distance to the nearest other point. Roughness: median over the sample
    of the RMS residual of the PCA plane through each point's ``neighbours`` nearest
    points (skipped, reported as nan, when ``roughness`` is False). Raises ComparisonError
    for clouds with fewer than ``neighbours`` points.
    """
    data = np.asarray(tree.data)
    if len(data) < max(2, neighbours):
        raise ComparisonError(f"cloud has {len(data)} points; need at least {neighbours}")
    # a seeded sample taken in the tree's own order: consecutive queries are spatial
    # neighbours (~2× faster than in the cloud's order on 1 M points)
    idx = np.asarray(tree.indices)[_sample(len(data), sample, seed)]
    dist, nn = tree.query(data[idx], k=neighbours if roughness else 2, workers=-1)
    spacing = float(np.median(dist[:, 1]))
    if not roughness:
        return CloudStats(spacing=spacing, roughness=float("nan"))
    nb = data[nn]  # (S, k, 3)
    centred = nb - nb.mean(axis=1, keepdims=True)
    cov = np.einsum("ski,skj->sij", centred, centred) / neighbours
    smallest = np.linalg.eigvalsh(cov)[:, 0]
    sigma = float(np.median(np.sqrt(np.clip(smallest, 0.0, None))))
    return CloudStats(spacing=spacing, roughness=sigma)


def lod_threshold(
    compared: CloudStats,
    reference: CloudStats,
    registration_m: float,
    z: float = 1.96,
    spacing_factor: float = 2.0,
) -> float:
    """Level of detection (metres) of C2C distances of ``compared`` against ``reference``."""
    noise = z**2 * (compared.roughness**2 + reference.roughness**2)
    sampling = (spacing_factor * reference.spacing) ** 2
    return float(np.sqrt(noise + sampling) + registration_m)


def clipped(distances: FloatArray, clip: float) -> FloatArray:
    """The (N,) distances at most median + ``clip`` × 1.4826 × MAD (a robust σ): the bulk
    of unchanged surface without the tail of large changes. Never empty."""
    median = float(np.median(distances))
    mad = float(np.median(np.abs(distances - median)))
    kept = distances[distances <= median + clip * 1.4826 * mad]
    return kept if kept.size else distances


def distance_stats(
    distances: ArrayLike,
    spec: ThresholdSpec,
    compared: CloudStats | None = None,
    reference: CloudStats | None = None,
    registration_m: float = 0.0,
    region: str = "all",
) -> DistanceStats:
    """Statistics and threshold of one side's (N,) distances (metres) under ``spec``.

    ``compared``/``reference`` stats are needed for ``lod`` (ComparisonError if missing).
    """
    d = np.asarray(distances, dtype=np.float64).reshape(-1)
    if d.size == 0:
        raise ComparisonError("no distances to threshold")
    mean, std = float(d.mean()), float(d.std())
    if spec.kind == "mean_std":
        kept = d if spec.clip is None else clipped(d, spec.clip)
        thr = float(kept.mean()) + spec.k * float(kept.std())
    elif spec.kind == "fixed":
        thr = float(spec.distance)
    else:
        if compared is None or reference is None:
            raise ComparisonError("the lod threshold needs both clouds' statistics")
        reg = registration_m if spec.registration is None else float(spec.registration)
        thr = lod_threshold(compared, reference, reg, spec.z, spec.spacing_factor)
    return DistanceStats(mean=mean, std=std, threshold=float(thr), n=int(d.size), region=region)
