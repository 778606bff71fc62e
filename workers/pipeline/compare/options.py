"""Options of the compare stage: a frozen dataclass with named presets.

The job row stores ``(preset name, overrides)``; :func:`options_from_json` rebuilds the
exact options, and :meth:`CompareOptions.to_json` writes them back.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

from workers.pipeline.errors import InputError

ThresholdKind = Literal["mean_std", "fixed", "lod"]


@dataclass(frozen=True)
class ThresholdSpec:
    """How a side's change threshold is chosen (distances in metres).

    - ``mean_std``: mean + k·std of the side's C2C distances (the thesis: k ∈ {0, .5, 1, 1.5}).
    - ``fixed``: ``distance``.
    - ``lod``: level of detection from roughness, spacing and registration,
      ``sqrt(z²(σ_q² + σ_r²) + (spacing_factor·s_r)²) + registration`` (see thresholds.py);
      ``registration`` None means "from the captures' alignment residuals".
      ``spacing_factor`` 2: for a Poisson-sampled surface, the 95 % quantile of the gap
      to the nearest sample is sqrt(ln 20 / ln 2) ≈ 2.08 × the median NN spacing.
    """

    kind: ThresholdKind = "mean_std"
    k: float = 1.0
    distance: float = 0.02
    z: float = 1.96
    spacing_factor: float = 2.0
    registration: float | None = None
    neighbours: int = 16

    def __post_init__(self) -> None:
        if self.kind not in ("mean_std", "fixed", "lod"):
            raise InputError(f"unknown threshold kind {self.kind!r}")
        if self.kind == "fixed" and not self.distance > 0:
            raise InputError("a fixed threshold needs distance > 0")
        if self.neighbours < 4:
            raise InputError("lod threshold needs neighbours ≥ 4")

    def to_json(self) -> dict[str, Any]:
        """The contract's short form, e.g. ``{"kind": "mean_std", "k": 1.0}``."""
        if self.kind == "mean_std":
            return {"kind": "mean_std", "k": self.k}
        if self.kind == "fixed":
            return {"kind": "fixed", "distance": self.distance}
        return {
            "kind": "lod",
            "z": self.z,
            "spacing_factor": self.spacing_factor,
            "registration": self.registration,
            "neighbours": self.neighbours,
        }

    @classmethod
    def from_json(cls, spec: Mapping[str, Any]) -> ThresholdSpec:
        """Parse the JSON form; raises InputError on unknown kinds or keys."""
        allowed = {f.name for f in dataclasses.fields(cls)}
        unknown = set(spec) - allowed
        if unknown:
            raise InputError(f"unknown threshold keys: {sorted(unknown)}")
        try:
            return cls(**dict(spec))
        except TypeError as exc:
            raise InputError(f"bad threshold spec: {exc}") from exc


@dataclass(frozen=True)
class CompareOptions:
    """Every knob of the compare stage. Lengths in metres, image sizes in pixels."""

    threshold: ThresholdSpec = field(default_factory=ThresholdSpec)
    # distance statistics over "overlap" (points where the other capture looked; a seeded
    # sample of ≤ stats_sample points) or "all" points (CloudCompare's figures)
    stats_region: Literal["overlap", "all"] = "overlap"
    stats_sample: int = 200_000
    # spacing estimate and clustering (DBSCAN over a radius graph)
    spacing_sample: int = 20_000
    cluster_radius_factor: float = 3.0
    cluster_min_samples: int = 4
    cluster_min_points: int = 30
    max_clusters: int = 100
    # hysteresis growth: clusters found at ``threshold`` take the connected points above
    # ``grow_threshold`` (capped at ``threshold``; None: no growth), e.g. an object's base
    # close to the old floor, or a low part of it (an L-bracket's foot). Reach: a path of at
    # most grow_max_diameters × the largest library diameter (no point of an object lies
    # further than its diameter from another); measured on the demo scene, a reach of
    # 1.5 × threshold (6 cm) left a removed L-bracket's foot out and it went unidentified
    grow_threshold: ThresholdSpec | None = field(default_factory=lambda: ThresholdSpec(kind="lod"))
    grow_max_diameters: float = 1.0
    # base growth (after hysteresis growth, only with it): a cluster takes the points
    # beneath its points, in columns of base_radius_factor × spacing, down to
    # base_band_factor × the side's grow threshold (0: off). Measured on the bench's removed
    # can (grow threshold 8 mm): without it its box lacked the lowest 3.6 px (median, 40
    # views); columns of 1 × spacing took a ring of floor and widened the box by 1.3 px;
    # 0.5 × spacing with a 2 × band: every edge within 1 px, mean IoU 0.826 → 0.850
    base_band_factor: float = 2.0
    base_radius_factor: float = 0.5
    # base growth only beneath the cluster's walls (its points with a point of it above them,
    # in the skirt-pruning column: skirt_radius_factor × spacing up to skirt_rise_m), not
    # beneath the smear sloping out from its foot, which has only floor below it. Measured on
    # the bench's moved mustard bottle, clean detector, planar prior on, same
    # reconstructions: 230 of the added cluster's 636 base points lay > 6 mm outside the
    # bottle, all on the floor, and its boxes were 2.0 px too wide left and right (median,
    # 40 views, against the true surface projected); with this 125 of 502, 1.4 px, metric
    # 0.796 -> 0.817 (its removed cluster 0.829 -> 0.832); hammer added 0.863 -> 0.875,
    # swapped 0.833 -> 0.848; 'multiple' +0.004..+0.011; the cans -0.003 (their boxes'
    # bottom edge 0.5 px higher: some of a can's lowest rim hangs from points with nothing
    # of the can above them)
    base_beneath_walls: bool = True
    # skirt pruning (after hysteresis growth, before base growth, only with growth): a grown
    # point with no point of its cluster above it (columns of skirt_radius_factor × spacing,
    # up to skirt_rise_m) within skirt_width_factor × spacing of the cluster's seeds is the
    # floor that stereo smears around an object's foot, and is dropped (0: off). Measured on
    # the bench's moved mustard bottle (same reconstructions): 345 of the 1008 grown points
    # lay > 6 mm off the object, and its boxes were 2.3 px too wide on the left, 1.4 px on
    # the right (median, 40 views); with 4 / 0.75: metric 0.803 -> 0.823, the two cans
    # -0.002 / 0, the hammer +0.001 (columns of 0.5 × spacing: mustard 0.823 but the cans
    # lost their lowest rim, -0.004)
    skirt_width_factor: float = 4.0
    skirt_radius_factor: float = 0.75
    skirt_rise_m: float = 0.03
    # visibility (z-buffer by point splatting at reduced resolution)
    use_visibility: bool = True
    zbuffer_max_side: int = 256
    zbuffer_max_points: int = 400_000
    zbuffer_fill_px: int = 1
    depth_tolerance_m: float = 0.02
    depth_tolerance_px: float = 2.0
    # a cluster's box in an image spans the [p, 100 − p] percentiles of its visible pixels;
    # measured on the bench scenes (YCB, boxes 30–140 px): p = 2 lost 3–6 % of mean IoU to
    # the trimmed edges, p = 0 let stray points widen it, p = 0.5 was best
    box_percentile: float = 0.5
    min_visible_points: int = 8
    # "not seen ≠ removed": a candidate counts only if ≥ min_seen_views of the other
    # capture's cameras see the space where it was as empty
    # "not seen ≠ added" likewise: new geometry counts only where the old capture saw empty
    # space (a hole in the old cloud is not an addition; measured on the demo scene:
    # 114 false floor-patch changes → 23 with it and 2 views)
    check_seen_removed: bool = True
    check_seen_added: bool = True
    min_seen_views: int = 2
    min_seen_fraction: float = 0.5
    # an unidentified cluster smaller than this is not reported as a change (it stays in the
    # clusters table): ~5 × 5 cm of surface at a 2.5 mm spacing
    unidentified_min_points: int = 300
    # merging clusters of one object
    merge_clusters: bool = True
    merge_containment: float = 0.6
    merge_shared_fraction: float = 0.5
    merge_size_margin: float = 1.25
    # identification (thesis eq. 3.1)
    identify_threshold: float = 0.5
    # change typing against the twin
    moved_max_distance: float = 5.0
    swap_distance_factor: float = 0.5
    instance_match_factor: float = 1.0
    instance_match_min: float = 0.25
    seed: int = 0

    def __post_init__(self) -> None:
        positive = (
            "spacing_sample",
            "stats_sample",
            "cluster_radius_factor",
            "cluster_min_samples",
            "cluster_min_points",
            "max_clusters",
            "zbuffer_max_side",
            "zbuffer_max_points",
            "min_visible_points",
            "min_seen_views",
            "unidentified_min_points",
            "merge_size_margin",
            "moved_max_distance",
        )
        for name in positive:
            if not getattr(self, name) > 0:
                raise InputError(f"option {name} must be > 0")
        if self.stats_region not in ("overlap", "all"):
            raise InputError("option stats_region must be 'overlap' or 'all'")
        if not 0.0 <= self.box_percentile < 50.0:
            raise InputError("option box_percentile must be in [0, 50)")
        if not 0.0 <= self.min_seen_fraction <= 1.0:
            raise InputError("option min_seen_fraction must be in [0, 1]")
        if isinstance(self.threshold, Mapping):
            object.__setattr__(self, "threshold", ThresholdSpec.from_json(self.threshold))
        if isinstance(self.grow_threshold, Mapping):
            spec = ThresholdSpec.from_json(self.grow_threshold)
            object.__setattr__(self, "grow_threshold", spec)
        if not self.grow_max_diameters >= 0:
            raise InputError("option grow_max_diameters must be ≥ 0")
        if not self.base_band_factor >= 0:
            raise InputError("option base_band_factor must be ≥ 0")
        if not self.base_radius_factor > 0:
            raise InputError("option base_radius_factor must be > 0")
        if not self.skirt_width_factor >= 0:
            raise InputError("option skirt_width_factor must be ≥ 0")
        if not (self.skirt_radius_factor > 0 and self.skirt_rise_m > 0):
            raise InputError("options skirt_radius_factor and skirt_rise_m must be > 0")

    def to_json(self) -> dict[str, Any]:
        """Plain JSON values; ``threshold`` in its short form."""
        out = dataclasses.asdict(self)
        out["threshold"] = self.threshold.to_json()
        grow = self.grow_threshold
        out["grow_threshold"] = None if grow is None else grow.to_json()
        return out

    def replace(self, **overrides: Any) -> CompareOptions:
        """A copy with ``overrides``; a ``threshold`` may be given as its JSON form."""
        known = {f.name for f in dataclasses.fields(self)}
        unknown = set(overrides) - known
        if unknown:
            raise InputError(f"unknown compare options: {sorted(unknown)}")
        for name in ("threshold", "grow_threshold"):
            if isinstance(overrides.get(name), Mapping):
                overrides[name] = ThresholdSpec.from_json(overrides[name])
        return dataclasses.replace(self, **overrides)


PRESETS: dict[str, CompareOptions] = {
    # occlusion-aware, merges split clusters, "not seen ≠ removed"
    "default": CompareOptions(),
    # the 2020 thesis as done by hand: no occlusion test, full box extent, no merging,
    # no visibility check for removals
    "thesis": CompareOptions(
        threshold=ThresholdSpec(kind="mean_std", k=1.0),
        stats_region="all",
        use_visibility=False,
        box_percentile=0.0,
        check_seen_removed=False,
        check_seen_added=False,
        grow_threshold=None,
        merge_clusters=False,
        unidentified_min_points=1,
    ),
    # the level of detection instead of a distribution quantile
    "lod": CompareOptions(threshold=ThresholdSpec(kind="lod")),
}


def options_from_json(
    preset: str = "default", overrides: Mapping[str, Any] | None = None
) -> CompareOptions:
    """Options from a preset name and overrides (as a job row stores them).

    Raises InputError for an unknown preset or option.
    """
    if preset not in PRESETS:
        raise InputError(f"unknown compare preset {preset!r}; known: {sorted(PRESETS)}")
    return PRESETS[preset].replace(**dict(overrides or {}))
