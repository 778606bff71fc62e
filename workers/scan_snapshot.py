"""The scan branch of the snapshot job (``source = scan``): the stored scan file → a cloud in
the environment frame at the density of the environment's photo clouds
(workers.pipeline.scan), returned as the reconstruct stage's result so the job persists it,
and moves the twin on, exactly as after a photo snapshot."""

from __future__ import annotations

from typing import Any

from app.core import scans
from workers.pipeline.reconstruct.markers import parse_reference
from workers.pipeline.reconstruct.options import options_from_preset
from workers.pipeline.reconstruct.stage import ReconstructionResult
from workers.pipeline.scan import ScanInput, ScanOptions, scan_to_cloud
from workers.progress import weighted
from workers.runner import JobContext

# Rough shares of a scan job's time, for one overall progress figure.
STAGE_WEIGHTS = {"read": 6, "markers": 3, "write": 1}


def compute(
    ctx: JobContext, prefix: str, reference: dict[str, Any] | None, options: dict[str, Any]
) -> ReconstructionResult:
    """Read the scan stored under ``prefix`` with the environment's ``reference`` (its
    marker sheet) and reconstruct ``options`` (whose voxel size sets the density)."""
    record = scans.load_record(ctx.storage, prefix)
    overrides = dict(options)
    preset = str(overrides.pop("preset", ctx.job.preset or "default"))
    voxel_m = options_from_preset(preset, **overrides).voxel_size_m
    sheet = parse_reference(reference) if record.frame.method == "markers" else None
    result = scan_to_cloud(
        ScanInput(
            path=ctx.storage.local_file(record.file_key),
            format=record.format,
            frame=record.frame,
            points_declared=record.points_declared,
        ),
        work_dir=ctx.work_dir / "scan",
        voxel_m=voxel_m,
        reference=sheet,
        options=ScanOptions(),
        progress=weighted(ctx.progress, STAGE_WEIGHTS),
    )
    return ReconstructionResult(
        cloud_path=result.cloud_path,
        cameras_path=result.cameras_path,
        quality_path=result.quality_path,
        views=(),
        quality=result.quality,
    )
