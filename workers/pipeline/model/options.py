"""How a library object is sampled and described: :class:`ModelOptions` and its presets."""

from __future__ import annotations

from dataclasses import dataclass, field

from workers.pipeline.model.detect_symmetry import SymmetryOptions

UNITS_TO_M: dict[str, float] = {"m": 1.0, "cm": 0.01, "mm": 0.001}


@dataclass(frozen=True)
class ModelOptions:
    """How a library object is sampled and described."""

    # size of the model cloud sampled from a mesh (a cloud is thinned to about this many)
    n_points: int = 6000
    # "poisson" (even blue-noise spacing) or "uniform" (area-weighted random, faster)
    sampling: str = "poisson"
    # feature voxel = diameter / this; raise for finer descriptors, costs time
    voxel_divisor: float = 25.0
    # FPFH normal radius, voxels
    normal_radius_voxels: float = 2.0
    # FPFH feature radius, voxels
    feature_radius_voxels: float = 5.0
    # viewpoints whose visible part gets its own descriptors (one-sided scans match them)
    feature_views: int = 12
    # seed of the sampling; preparation is reproducible for a seed
    seed: int = 0
    # how symmetries are detected
    symmetry: SymmetryOptions = field(default_factory=SymmetryOptions)


MODEL_PRESETS: dict[str, ModelOptions] = {
    "default": ModelOptions(),
    "fast": ModelOptions(n_points=3000, sampling="uniform"),
    "fine": ModelOptions(n_points=12000, voxel_divisor=35.0),
}
