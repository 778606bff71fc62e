"""Options of the inventory stage: a frozen dataclass with named presets.

The snapshot job stores ``{"preset": name, **overrides}`` (the environment's
``options["inventory"]``); :func:`inventory_options_from_json` rebuilds the exact options.
Lengths in metres. The clustering, identification and visibility settings are the compare
stage's (``compare_preset`` and ``compare``), so a segment is named by the same metric and
threshold as a changed cluster; the pose settings are the pose stage's (``pose``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from workers.pipeline.compare.options import CompareOptions, options_from_json
from workers.pipeline.errors import InputError
from workers.pipeline.option_values import with_overrides
from workers.pipeline.pose.options import PoseOptions, pose_options_from_json


@dataclass(frozen=True)
class InventoryOptions:
    """Every knob of the inventory stage (one line each: meaning, unit, when to change it)."""

    # support surfaces
    # height histogram bin of the support search, metres; rarely changed
    support_bin_m: float = 0.005
    # half-height of the slab a support's points are taken from, metres
    support_slab_m: float = 0.015
    # raster cell of a support's footprint, metres
    support_cell_m: float = 0.02
    # least area of a support after opening, m²; lower to find small shelves
    min_support_area_m2: float = 0.08
    # supports are level planes (the environment frame's z is up, set by the floor's
    # markers); False fits each plane's tilt too (a tilted frame, a sloping floor)
    level_supports: bool = True
    # a raster column with more occupied height bins than this is a vertical surface (wall,
    # furniture side, object flank), left out of the support search
    column_max_bins: int = 12
    # the most populated height peaks examined as supports; raise for many shelf boards
    max_support_peaks: int = 16
    # ... and at least this × the largest library diameter squared (an object's top is
    # not a support)
    support_area_diameters: float = 0.5
    # closing of a slab's raster before the opening, cells: bridges the holes of a sparsely
    # reconstructed top (a plain table); lower if separate surfaces of one height merge
    support_closing_cells: int = 3
    # opening of the footprint raster, cells (removes walls: thin lines in the raster)
    support_opening_cells: int = 2
    # holes of the footprint up to this × the largest library diameter are filled (the
    # floor beneath an object is never seen)
    footprint_close_diameters: float = 0.6
    # segmentation
    # a point stands on a support when it is this many noise sigmas above it ...
    band_sigmas: float = 3.0
    # ... and at least this high, metres; lower to keep flat objects' lower parts
    band_min_m: float = 0.004
    # growth band (hysteresis, the compare stage's growth and skirt pruning): × the band;
    # 0 = no growth; lower reaches flat objects' feet but more of the floor's noise
    grow_band_factor: float = 0.8
    # points higher above their support than this × the largest diameter are not objects
    max_height_diameters: float = 1.1
    # segments longer than this × the largest diameter (walls, furniture) are dropped
    max_extent_diameters: float = 1.6
    # two objects of one class closer than this × its diameter are one (a split segment)
    duplicate_diameters: float = 0.5
    # an object counts only when its posed model re-projects onto the detector's boxes
    require_reprojection: bool = True
    # the compare stage's preset for clustering, visibility and identification
    compare_preset: str = "default"
    # overrides of that preset (its JSON form)
    compare: Mapping[str, Any] = field(default_factory=dict)
    # the pose stage's options (``{"preset": name, **overrides}``)
    pose: Mapping[str, Any] = field(default_factory=dict)
    # seed of every sample the stage draws (spacing sample; compare and pose have their own)
    seed: int = 0

    def __post_init__(self) -> None:
        positive = (
            "support_bin_m",
            "support_slab_m",
            "support_cell_m",
            "min_support_area_m2",
            "support_area_diameters",
            "band_sigmas",
            "max_height_diameters",
            "max_extent_diameters",
            "max_support_peaks",
            "column_max_bins",
        )
        for name in positive:
            if not getattr(self, name) > 0:
                raise InputError(f"inventory option {name} must be > 0")
        for name in ("band_min_m", "grow_band_factor", "footprint_close_diameters"):
            if not getattr(self, name) >= 0:
                raise InputError(f"inventory option {name} must be ≥ 0")
        if self.grow_band_factor >= 1:
            raise InputError("inventory option grow_band_factor must be < 1")
        for name in ("support_closing_cells", "support_opening_cells"):
            if getattr(self, name) < 0:
                raise InputError(f"inventory option {name} must be ≥ 0")
        self.compare_options()  # InputError now rather than mid-job
        self.pose_options()

    def compare_options(self) -> CompareOptions:
        """The compare stage's options this inventory clusters and identifies with."""
        return options_from_json(self.compare_preset, dict(self.compare))

    def pose_options(self) -> PoseOptions:
        """The pose stage's options this inventory poses with."""
        return pose_options_from_json(dict(self.pose))

    def to_json(self) -> dict[str, Any]:
        """Plain JSON values (``compare``/``pose`` as given)."""
        out = dataclasses.asdict(self)
        out["compare"], out["pose"] = dict(self.compare), dict(self.pose)
        return out


INVENTORY_PRESETS: dict[str, InventoryOptions] = {
    "default": InventoryOptions(),
    # the pose stage's fast preset: one round of three seeds per object
    "fast": InventoryOptions(pose={"preset": "fast"}),
}


def inventory_options_from_json(options: Mapping[str, Any] | None) -> InventoryOptions:
    """Options from ``{"preset": name, **overrides}``; InputError for an unknown preset or
    option, or a value of the wrong type."""
    overrides = dict(options or {})
    preset = str(overrides.pop("preset", "default"))
    nested = {k: overrides.pop(k) for k in ("compare", "pose") if k in overrides}
    for key, value in nested.items():
        if not isinstance(value, Mapping):
            raise InputError(f"inventory option {key} must be an object, got {value!r}")
    base = with_overrides("inventory", INVENTORY_PRESETS, preset, overrides)
    return dataclasses.replace(base, **nested) if nested else base
