"""Synthetic before/after captures with exact ground truth (pure; no service imports).

``generate(out_dir, scenario, seed, options, models)`` writes one scenario;
``build_scenario`` / ``render_capture`` / ``true_surfaces`` give the same scene in memory.
"""

from workers.pipeline.synth.generate import (
    CAPTURES,
    Detection,
    detect,
    generate,
    ground_truth,
    load_true_surfaces,
    render_capture,
    true_surfaces,
    visible_boxes,
    yolo_lines,
)
from workers.pipeline.synth.options import (
    PRESETS,
    SCENARIOS,
    CameraOptions,
    DetectionOptions,
    LookOptions,
    PathOptions,
    RoomOptions,
    SynthOptions,
    preset,
)
from workers.pipeline.synth.scene import Placement, Scenario, build_scenario
from workers.pipeline.synth.shapes import ObjectModel, builtin_models, load_model

__all__ = [
    "CAPTURES",
    "PRESETS",
    "SCENARIOS",
    "CameraOptions",
    "Detection",
    "DetectionOptions",
    "LookOptions",
    "ObjectModel",
    "PathOptions",
    "Placement",
    "RoomOptions",
    "Scenario",
    "SynthOptions",
    "build_scenario",
    "builtin_models",
    "detect",
    "generate",
    "ground_truth",
    "load_model",
    "load_true_surfaces",
    "preset",
    "render_capture",
    "true_surfaces",
    "visible_boxes",
    "yolo_lines",
]
