"""``python -m workers.pipeline reconstruct <images_dir> --out DIR [--cameras cameras.json]
[--reference reference.json] [--reference-cloud prev.ply] [--preset NAME] [--set key=value]``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from workers.pipeline.errors import PipelineError
from workers.pipeline.reconstruct.cameras import load_cameras
from workers.pipeline.reconstruct.options import PRESETS, options_from_preset
from workers.pipeline.reconstruct.stage import reconstruct


def _value(text: str) -> Any:
    try:
        return json.loads(text)
    except ValueError:
        return text


def cli(argv: list[str]) -> int:
    """Run the reconstruct stage; prints quality JSON. Exit 0 ok, 1 pipeline error, 2 usage."""
    parser = argparse.ArgumentParser(prog="python -m workers.pipeline reconstruct")
    parser.add_argument("images_dir", type=Path)
    parser.add_argument("--out", type=Path, required=True, help="work directory for outputs")
    parser.add_argument("--cameras", type=Path, help="cameras.json (intrinsics, poses)")
    parser.add_argument("--reference", type=Path, help="environment reference JSON (markers)")
    parser.add_argument("--reference-cloud", type=Path, help="previous snapshot's cloud (PLY)")
    parser.add_argument("--preset", default="default", choices=sorted(PRESETS))
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args(argv)
    try:
        overrides = dict(item.split("=", 1) for item in args.set)
        options = options_from_preset(args.preset, **{k: _value(v) for k, v in overrides.items()})
        cameras = load_cameras(args.cameras) if args.cameras else None
        reference = json.loads(args.reference.read_text()) if args.reference else None
        if reference is not None and "reference" in reference and "markers" not in reference:
            reference = reference["reference"]

        def progress(stage: str, fraction: float) -> None:
            if not args.quiet:
                print(f"{stage} {fraction:.2f}", file=sys.stderr)

        result = reconstruct(
            args.images_dir, args.out, options, cameras, reference, args.reference_cloud, progress
        )
    except PipelineError as exc:
        print(json.dumps({"error": exc.code, "detail": exc.detail}))
        return 1
    except (OSError, ValueError) as exc:
        print(json.dumps({"error": "InvalidInput", "detail": str(exc)}))
        return 2
    print(json.dumps(result.quality, indent=1, default=str))
    return 0
