"""How a library object is sampled and described: :class:`ModelOptions` and its presets."""

from __future__ import annotations

from dataclasses import dataclass, field

from workers.pipeline.model.detect_symmetry import SymmetryOptions

UNITS_TO_M: dict[str, float] = {"m": 1.0, "cm": 0.01, "mm": 0.001}


@dataclass(frozen=True)
class ModelOptions:
    """How a library object is sampled and described.

    ``n_points``: size of the model cloud sampled from a mesh (clouds are thinned to about
    this many points). ``sampling``: ``"poisson"`` (blue-noise sample elimination over a
    5× uniform sample, even spacing) or ``"uniform"`` (area-weighted random). ``voxel_divisor``:
    the feature voxel is ``diameter / voxel_divisor``; FPFH uses a normal radius of
    ``normal_radius_voxels`` and a feature radius of ``feature_radius_voxels`` voxels.
    ``feature_views``: besides whole-model FPFH, descriptors of the part visible from this
    many viewpoints (hidden-point removal) are stored, so that a one-sided scan finds
    matching descriptors. ``seed`` makes sampling reproducible.
    """

    n_points: int = 6000
    sampling: str = "poisson"
    voxel_divisor: float = 25.0
    normal_radius_voxels: float = 2.0
    feature_radius_voxels: float = 5.0
    feature_views: int = 12
    seed: int = 0
    symmetry: SymmetryOptions = field(default_factory=SymmetryOptions)


MODEL_PRESETS: dict[str, ModelOptions] = {
    "default": ModelOptions(),
    "fast": ModelOptions(n_points=3000, sampling="uniform"),
    "fine": ModelOptions(n_points=12000, voxel_divisor=35.0),
}
