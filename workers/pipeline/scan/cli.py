"""``python -m workers.pipeline scan <scan file> --out DIR (--frame '{"transform": ...}' |
--frame '{"markers": true}' --reference reference.json) [--voxel 0.0025]``: the scan stage
without the service; prints the quality JSON."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from app.formats import FormatError
from app.formats.scan import SNIFF_BYTES, parse_scan_frame, sniff_scan_format
from workers.pipeline.errors import PipelineError
from workers.pipeline.reconstruct.markers import parse_reference
from workers.pipeline.reconstruct.options import ReconstructOptions
from workers.pipeline.scan.options import ScanOptions
from workers.pipeline.scan.stage import ScanInput, scan_to_cloud


def cli(argv: list[str]) -> int:
    """Run the scan stage. Exit 0 ok, 1 pipeline error, 2 usage or unreadable input."""
    parser = argparse.ArgumentParser(prog="python -m workers.pipeline scan")
    parser.add_argument("scan", type=Path, help="E57, LAS, LAZ or PLY file")
    parser.add_argument("--out", type=Path, required=True, help="work directory for outputs")
    parser.add_argument("--frame", required=True, help='{"transform": 4×4} or {"markers": true}')
    parser.add_argument("--reference", type=Path, help="environment reference JSON (markers)")
    parser.add_argument("--voxel", type=float, default=ReconstructOptions().voxel_size_m)
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args(argv)
    try:
        with args.scan.open("rb") as fh:
            fmt = sniff_scan_format(fh.read(SNIFF_BYTES))
        if fmt is None:
            raise ValueError(f"{args.scan}: not an E57, LAS, LAZ or PLY file")
        frame = parse_scan_frame(args.frame)
        reference = json.loads(args.reference.read_text()) if args.reference else None

        def progress(stage: str, fraction: float) -> None:
            if not args.quiet:
                print(f"{stage} {fraction:.2f}", file=sys.stderr)

        result = scan_to_cloud(
            ScanInput(args.scan, fmt, frame),
            args.out,
            args.voxel,
            parse_reference(reference),
            ScanOptions(),
            progress,
        )
    except PipelineError as exc:
        print(json.dumps({"error": exc.code, "detail": exc.detail}))
        return 1
    except (OSError, ValueError, FormatError) as exc:
        print(json.dumps({"error": "InvalidInput", "detail": str(exc)}))
        return 2
    print(json.dumps(result.quality, indent=1))
    return 0
