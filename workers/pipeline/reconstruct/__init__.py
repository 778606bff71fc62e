"""Reconstruct stage: SfM (or given poses) → env frame from markers → CPU MVS → fused cloud.

Public API: :func:`reconstruct`, :class:`ReconstructOptions`, :func:`options_from_preset`,
:class:`ReconstructionResult`, :class:`CamerasSpec`, :func:`load_cameras`.
"""

from workers.pipeline.reconstruct.cameras import (
    CamerasSpec,
    CameraView,
    Intrinsics,
    load_cameras,
    parse_cameras,
)
from workers.pipeline.reconstruct.options import PRESETS, ReconstructOptions, options_from_preset
from workers.pipeline.reconstruct.stage import ReconstructionResult, reconstruct

__all__ = [
    "PRESETS",
    "CameraView",
    "CamerasSpec",
    "Intrinsics",
    "ReconstructOptions",
    "ReconstructionResult",
    "load_cameras",
    "options_from_preset",
    "parse_cameras",
    "reconstruct",
]
