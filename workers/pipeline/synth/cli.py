"""``python -m workers.pipeline synth --scenario moved --out DIR [--seed 0] [--preset demo]
[--ycb DIR --objects power_drill,mustard_bottle,...] [--views N] [--poses | --no-poses]
[--room closed|one_wall|...] [--path ring|low_high|wide_high] [--real-camera]
[--distractors column,unknown_box] [--target NAME] [--lying NAME,...]``."""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

from workers.pipeline.errors import PipelineError
from workers.pipeline.synth.generate import generate
from workers.pipeline.synth.options import (
    DISTRACTORS,
    PATH_PRESETS,
    PRESETS,
    REAL_CAMERA,
    ROOM_PRESETS,
    SCENARIOS,
    SynthOptions,
    preset,
)
from workers.pipeline.synth.shapes import ObjectModel, load_model


def _models(ycb: Path | None, objects: str | None) -> list[ObjectModel] | None:
    """YCB models named in ``objects`` (comma-separated) under ``ycb``; None = built-ins."""
    if objects is None:
        return None
    names = [n.strip() for n in objects.split(",") if n.strip()]
    if ycb is None:
        return [load_model(Path(n)) for n in names]
    return [load_model(ycb / n / "textured.obj", n) for n in names]


def _world(options: SynthOptions, args: argparse.Namespace) -> SynthOptions:
    """``options`` with the room, path, effects, distractors, target and lying objects of
    the arguments."""
    if args.room is not None:
        options = replace(options, room=ROOM_PRESETS[args.room])
    if args.path is not None:
        path = replace(PATH_PRESETS[args.path], n_views=options.path.n_views)
        options = replace(options, path=path)
    if args.real_camera:
        options = replace(options, effects=REAL_CAMERA)
    if args.distractors:
        names = tuple(n.strip() for n in args.distractors.split(",") if n.strip())
        options = replace(options, distractors=names)
    if args.lying:
        lying = tuple(n.strip() for n in args.lying.split(",") if n.strip())
        options = replace(options, lying=lying)
    return replace(options, target=args.target)


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
    parser.add_argument("--room", choices=sorted(ROOM_PRESETS), help="room layout preset")
    parser.add_argument("--path", choices=sorted(PATH_PRESETS), help="camera path preset")
    parser.add_argument(
        "--real-camera", action="store_true", help="lens distortion, exposure, blur"
    )
    parser.add_argument("--distractors", help=f"comma-separated, of {', '.join(DISTRACTORS)}")
    parser.add_argument("--target", help="the object the change acts on")
    parser.add_argument(
        "--lying",
        help="comma-separated objects set down on a side or upside down, not on their base",
    )
    args = parser.parse_args(argv)
    options = _world(preset(args.preset), args)
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
