"""``python -m workers.pipeline synth --scenario moved --out DIR [--seed 0] [--preset demo]
[--ycb DIR --objects power_drill,mustard_bottle,...] [--views N] [--poses | --no-poses]``."""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

from workers.pipeline.errors import PipelineError
from workers.pipeline.synth.generate import generate
from workers.pipeline.synth.options import PRESETS, SCENARIOS, preset
from workers.pipeline.synth.shapes import ObjectModel, load_model


def _models(ycb: Path | None, objects: str | None) -> list[ObjectModel] | None:
    """YCB models named in ``objects`` (comma-separated) under ``ycb``; None = built-ins."""
    if objects is None:
        return None
    names = [n.strip() for n in objects.split(",") if n.strip()]
    if ycb is None:
        return [load_model(Path(n)) for n in names]
    return [load_model(ycb / n / "textured.obj", n) for n in names]


def cli(argv: list[str]) -> int:
    """Generate one before/after scenario; returns the process exit status."""
    parser = argparse.ArgumentParser(prog="python -m workers.pipeline synth", description=__doc__)
    parser.add_argument("--scenario", choices=SCENARIOS, required=True)
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--preset", choices=sorted(PRESETS), default="demo")
    parser.add_argument("--ycb", type=Path, help="folder of <name>/textured.obj models")
    parser.add_argument(
        "--objects", help="comma-separated model names (with --ycb) or mesh file paths"
    )
    parser.add_argument("--views", type=int, help="override the preset's number of views")
    poses = parser.add_mutually_exclusive_group()
    poses.add_argument(
        "--poses",
        dest="poses",
        action="store_true",
        default=None,
        help="write the true camera poses into cameras.json",
    )
    poses.add_argument("--no-poses", dest="poses", action="store_false")
    args = parser.parse_args(argv)
    options = preset(args.preset)
    if args.views is not None:
        options = replace(options, path=replace(options.path, n_views=args.views))
    if args.poses is not None:
        options = replace(options, write_poses=args.poses)
    try:
        scene = generate(
            args.out, args.scenario, args.seed, options, _models(args.ycb, args.objects)
        )
    except PipelineError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(
        f"{scene.name}: {len(scene.before)} → {len(scene.after)} objects, "
        f"{len(scene.changes)} change(s), written to {args.out}"
    )
    return 0
