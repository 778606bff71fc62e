"""Compare stage: C2C both ways, thresholds, clusters, visibility-aware identification and
change types against the twin. Entry point: :func:`compare_snapshots`."""

from workers.pipeline.compare.c2c import C2CResult, c2c, c2c_both_ways
from workers.pipeline.compare.data import Camera, CaptureData, TwinInstance, as_detections
from workers.pipeline.compare.options import (
    PRESETS,
    CompareOptions,
    ThresholdSpec,
    options_from_json,
)
from workers.pipeline.compare.results import Change, ClusterResult, CompareResult
from workers.pipeline.compare.stage import compare_snapshots
from workers.pipeline.compare.thresholds import DistanceStats, distance_stats

__all__ = [
    "PRESETS",
    "C2CResult",
    "Camera",
    "CaptureData",
    "Change",
    "ClusterResult",
    "CompareOptions",
    "CompareResult",
    "DistanceStats",
    "ThresholdSpec",
    "TwinInstance",
    "as_detections",
    "c2c",
    "c2c_both_ways",
    "compare_snapshots",
    "distance_stats",
    "options_from_json",
]
