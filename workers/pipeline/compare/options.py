"""Options of the compare stage: a frozen dataclass with named presets.

The job row stores ``(preset name, overrides)``; :func:`options_from_json` rebuilds the
exact options, and :meth:`CompareOptions.to_json` writes them back. Each option's comment
says what it is, its unit and when to change it; why each default is what it is (the
measurements) is in docs/decisions/compare.md.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

from workers.pipeline.errors import InputError
from workers.pipeline.option_values import with_overrides

ThresholdKind = Literal["mean_std", "fixed", "lod"]
StatsRegion = Literal["overlap", "all"]


@dataclass(frozen=True)
class ThresholdSpec:
    """How a side's change threshold is chosen (distances in metres).

    - ``mean_std``: mean + k·std of the side's C2C distances (the thesis: k ∈ {0, .5, 1, 1.5}),
      with ``clip`` over the distances up to median + clip·1.4826·MAD only, so that one
      large change (a column, 10 % of the points) cannot lift it above smaller ones.
    - ``fixed``: ``distance``.
    - ``lod``: level of detection from roughness, spacing and registration,
      ``sqrt(z²(σ_q² + σ_r²) + (spacing_factor·s_r)²) + registration`` (see thresholds.py);
      ``registration`` None means "from the captures' alignment residuals".
      ``spacing_factor`` 2: for a Poisson-sampled surface, the 95 % quantile of the gap
      to the nearest sample is sqrt(ln 20 / ln 2) ≈ 2.08 × the median NN spacing.
    """

    # "mean_std", "fixed" or "lod" (see the class docstring)
    kind: ThresholdKind = "mean_std"
    # mean_std: standard deviations above the mean; lower to catch smaller changes
    k: float = 1.0
    # mean_std: leave out distances above median + clip × 1.4826 × MAD (None: keep all)
    clip: float | None = None
    # fixed: the threshold, metres
    distance: float = 0.02
    # lod: normal quantile of the noise term (1.96: 95 %)
    z: float = 1.96
    # lod: sampling gap as a multiple of the reference's median spacing
    spacing_factor: float = 2.0
    # lod: registration error between the captures, metres (None: from their residuals)
    registration: float | None = None
    # lod: neighbours of the local plane that roughness is measured on
    neighbours: int = 16

    def __post_init__(self) -> None:
        if self.kind not in ("mean_std", "fixed", "lod"):
            raise InputError(f"unknown threshold kind {self.kind!r}")
        if self.kind == "fixed" and not self.distance > 0:
            raise InputError("a fixed threshold needs distance > 0")
        if self.neighbours < 4:
            raise InputError("lod threshold needs neighbours ≥ 4")
        if self.clip is not None and not self.clip > 0:
            raise InputError("a mean_std threshold's clip must be > 0 or null")

    def to_json(self) -> dict[str, Any]:
        """The contract's short form, e.g. ``{"kind": "mean_std", "k": 1.0}``."""
        if self.kind == "mean_std":
            if self.clip is None:
                return {"kind": "mean_std", "k": self.k}
            return {"kind": "mean_std", "k": self.k, "clip": self.clip}
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

    # thresholds
    # how each side's change threshold on C2C distances is chosen (see ThresholdSpec); the
    # clip lets a small change beside a large one through (and surface noise, which the
    # evidence checks of unidentified clusters then drop); clip None for the thesis's level
    threshold: ThresholdSpec = field(default_factory=lambda: ThresholdSpec(clip=6.0))
    # distance statistics over "overlap" (points the other capture looked at) or "all" points
    stats_region: StatsRegion = "overlap"
    # at most this many points (seeded sample) for the overlap test of the statistics
    stats_sample: int = 200_000
    # clustering
    # points (seeded sample) the median spacing and roughness are estimated from
    spacing_sample: int = 20_000
    # DBSCAN radius, × the median point spacing; raise when objects break into many clusters
    cluster_radius_factor: float = 3.0
    # DBSCAN core points need this many neighbours within the radius
    cluster_min_samples: int = 4
    # a cluster needs at least this many points; lower to keep small objects
    cluster_min_points: int = 30
    # the largest clusters kept per side
    max_clusters: int = 100
    # hysteresis growth
    # lower threshold clusters grow through (capped at threshold); None: no growth
    grow_threshold: ThresholdSpec | None = field(default_factory=lambda: ThresholdSpec(kind="lod"))
    # growth reach along connected points, × the largest library diameter
    grow_max_diameters: float = 1.0
    # base growth
    # depth of the band beneath a cluster it takes, × the side's grow threshold (0: off)
    base_band_factor: float = 2.0
    # width of the columns base growth looks down, × the median point spacing
    base_radius_factor: float = 0.5
    # grow the base only beneath the cluster's walls, not beneath the smear around its foot
    base_beneath_walls: bool = True
    # skirt pruning
    # grown points with nothing of the cluster above them, within this × spacing of the
    # seeds, are floor smeared around the foot and dropped (0: off)
    skirt_width_factor: float = 4.0
    # width of the columns skirt pruning looks up (and walls are found in), × spacing
    skirt_radius_factor: float = 0.75
    # how far up a column is searched for the cluster's own points, metres
    skirt_rise_m: float = 0.03
    # visibility
    # test occlusion with z-buffers of each capture's own cloud; False: in image = visible
    use_visibility: bool = True
    # long side of the z-buffers, pixels; raise for finer occlusion at more memory and time
    zbuffer_max_side: int = 256
    # at most this many points (seeded sample) splatted into the z-buffers
    zbuffer_max_points: int = 400_000
    # splat radius of each point in the z-buffer, pixels; raise for sparse clouds
    zbuffer_fill_px: int = 1
    # a point is visible within this depth of the z-buffer, metres (plus depth_tolerance_px)
    depth_tolerance_m: float = 0.02
    # extra depth tolerance: the depth span of this many pixels at the point's depth
    depth_tolerance_px: float = 2.0
    # a cluster's box spans the [p, 100 − p] percentiles of its visible pixels, percent
    box_percentile: float = 0.5
    # a cluster is visible in an image when at least this many of its points are
    min_visible_points: int = 8
    # a visible cluster counts as an occurrence in an image only where its box has at
    # least this area, pixels² (where the detector could fire); set near the detector's
    # smallest box
    min_box_area_px: float = 150.0
    # not seen is not changed
    # a removed candidate counts only where the after capture saw empty space
    check_seen_removed: bool = True
    # an unidentified added cluster counts only where the before capture saw empty space
    check_seen_added: bool = True
    # views that must see the space as empty for a point to count as seen
    min_seen_views: int = 2
    # share of an unidentified added cluster's points that must be seen as empty
    min_seen_fraction: float = 0.5
    # a place is seen empty where the other capture's surface lies this far behind the
    # point, metres (plus seen_tolerance_px); lower to see flat objects go, raise for
    # noisy clouds
    seen_tolerance_m: float = 0.005
    # extra seen-check tolerance: the depth span of this many z-buffer pixels
    seen_tolerance_px: float = 1.0
    # a camera's view through a place counts only where its photo shows the colour of the
    # surface behind (every RGB channel within this, 0-1, gains matched): the cloud can
    # miss an object the photo shows; None: depth alone. Raise for noisy colours
    seen_colour_tolerance: float | None = 0.1
    # long side of the seen checks' own z-buffers, pixels (None: zbuffer_max_side's);
    # finer ones see lower objects go, at more time
    seen_zbuffer_max_side: int | None = 512
    # reporting
    # smallest unidentified cluster reported as a change, points (~5 × 5 cm at 2.5 mm spacing)
    unidentified_min_points: int = 300
    # merging
    # merge clusters that the same detection box contains (an object split in parts)
    merge_clusters: bool = True
    # share of a cluster's box a detection must contain to claim it
    merge_containment: float = 0.6
    # share of images two clusters must share a detection in to merge
    merge_shared_fraction: float = 0.5
    # merged extent may exceed the class diameter by this factor
    merge_size_margin: float = 1.25
    # identification and change types
    # smallest identification metric (mean IoU × overlaps / occurrences) that names a cluster
    identify_threshold: float = 0.5
    # both boxes of an IoU are padded by this fraction of the image's longer side: about
    # twice the detector's box-edge noise; raise for a noisier detector
    box_margin: float = 0.005
    # a removed and an added cluster of one class further apart than this are not a move, metres
    moved_max_distance: float = 5.0
    # a swap's clusters lie closer than this × the larger of the two diameters
    swap_distance_factor: float = 0.5
    # a removed cluster the detector does not name takes the class of the twin instance it
    # lies on, an added one standing where an identified object was removed its best
    # other class, and the best cluster elsewhere for the class of an identified cluster
    # with no counterpart (a move's other end) that class, when it scores at least this
    # metric; an inventory segment scoring it is posed as its best class and named when
    # the posed model scores identify_threshold (None: off)
    twin_identify_threshold: float | None = 0.3
    # an identified cluster left as a plain addition or removal is no change when the
    # other capture's detector names its class at its place with at least this metric
    # (a hole in one reconstruction); None: off
    still_there_metric: float | None = 0.3
    # a removed cluster closes a twin instance within this × its class diameter
    instance_match_factor: float = 1.0
    # smallest reach of that match, metres (instance_match_factor × diameter if larger)
    instance_match_min: float = 0.25
    # randomness
    # seed of every sample the stage draws (z-buffer points, spacing and statistics samples)
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
        if not 0.0 <= self.box_margin < 0.1:
            raise InputError("option box_margin must be in [0, 0.1)")
        self._check_evidence_options()
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

    def _check_evidence_options(self) -> None:
        """Ranges of the occurrence, seen-check and cross-evidence options."""
        if not self.min_box_area_px >= 0:
            raise InputError("option min_box_area_px must be ≥ 0")
        if not (self.seen_tolerance_m >= 0 and self.seen_tolerance_px >= 0):
            raise InputError("options seen_tolerance_m and seen_tolerance_px must be ≥ 0")
        if self.seen_zbuffer_max_side is not None and not self.seen_zbuffer_max_side > 0:
            raise InputError("option seen_zbuffer_max_side must be > 0 or null")
        if self.seen_colour_tolerance is not None and not 0 < self.seen_colour_tolerance <= 1:
            raise InputError("option seen_colour_tolerance must be in (0, 1] or null")
        for name in ("twin_identify_threshold", "still_there_metric"):
            value = getattr(self, name)
            if value is not None and not 0.0 < value <= 1.0:
                raise InputError(f"option {name} must be in (0, 1] or null")

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
        box_margin=0.0,
        check_seen_removed=False,
        check_seen_added=False,
        grow_threshold=None,
        merge_clusters=False,
        unidentified_min_points=1,
        min_box_area_px=0.0,
        twin_identify_threshold=None,
        still_there_metric=None,
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
    return with_overrides("compare", PRESETS, preset, overrides)
