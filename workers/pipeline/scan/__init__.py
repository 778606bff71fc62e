"""Laser scans as snapshots: read an E57, LAS, LAZ or PLY scan in chunks, put it in the
environment frame (a given ``env_from_scan``, or the marker sheet found in the scan) and
write it as a photo snapshot's cloud. :func:`scan_to_cloud` is the stage; :mod:`.read` the
readers, :mod:`.voxels` the streaming voxel averaging, :mod:`.markers` the sheet in a
coloured cloud, :mod:`.options` the options."""

from workers.pipeline.scan.markers import NoUsableFrame, SheetFit, find_sheet, kabsch
from workers.pipeline.scan.options import PRESETS, ScanOptions, scan_options
from workers.pipeline.scan.read import ScanChunk, ScanReadError, iter_scan
from workers.pipeline.scan.stage import EmptyScan, ScanInput, ScanResult, scan_to_cloud
from workers.pipeline.scan.voxels import ScanTooDense, VoxelGrid

__all__ = [
    "PRESETS",
    "EmptyScan",
    "NoUsableFrame",
    "ScanChunk",
    "ScanInput",
    "ScanOptions",
    "ScanReadError",
    "ScanResult",
    "ScanTooDense",
    "SheetFit",
    "VoxelGrid",
    "find_sheet",
    "iter_scan",
    "kabsch",
    "scan_options",
    "scan_to_cloud",
]
