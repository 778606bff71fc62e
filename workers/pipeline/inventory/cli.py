"""``python -m workers.pipeline inventory CAPTURE_DIR --model NAME=MODEL_DIR ... [options]``.

Reads a capture folder as the compare stage does (``cloud.ply``, ``cameras.json``, YOLO
labels from ``--labels`` or ``CAPTURE_DIR/labels``; a ``reconstruct`` output folder is
one), the classes (``--classes``, default ``CAPTURE_DIR/classes.txt``) and the prepared
library models (``--model name=dir``, the work folders of ``python -m workers.pipeline
model``), takes the inventory and writes its JSON to ``--out`` or stdout. Exit codes: 0 ok,
2 bad input, 3 the inventory failed.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from workers.pipeline.compare.files import load_capture, load_classes
from workers.pipeline.errors import InputError, PipelineError
from workers.pipeline.inventory.options import INVENTORY_PRESETS, inventory_options_from_json
from workers.pipeline.inventory.stage import take_inventory
from workers.pipeline.model import PreparedModel, load_prepared


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m workers.pipeline inventory", description=__doc__)
    p.add_argument("capture", type=Path, help="capture folder (cloud.ply, cameras.json)")
    p.add_argument("--labels", type=Path, help="YOLO labels folder (default CAPTURE/labels)")
    p.add_argument("--classes", type=Path, help="classes.txt (default CAPTURE/classes.txt)")
    p.add_argument(
        "--model", action="append", default=[], metavar="NAME=DIR", help="a prepared model"
    )
    p.add_argument("--preset", default="default", choices=sorted(INVENTORY_PRESETS))
    p.add_argument("--options", default="{}", help="JSON overrides of the preset")
    p.add_argument("--out", type=Path, help="write the inventory JSON here (default stdout)")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    return p


def cli(argv: list[str]) -> int:
    """Run the inventory stage from the command line; returns the exit code."""
    args = _parser().parse_args(argv)
    try:
        classes = load_classes(args.classes or args.capture / "classes.txt")
        models: dict[str, PreparedModel] = {}
        for spec in args.model:
            name, sep, folder = spec.partition("=")
            if not sep or not name or not folder:
                raise InputError(f"--model wants NAME=DIR, got {spec!r}")
            models[name] = load_prepared(Path(folder))
        overrides = json.loads(args.options)
        if not isinstance(overrides, dict):
            raise InputError("--options must be a JSON object")
        options = inventory_options_from_json({"preset": args.preset, **overrides})
        capture = load_capture(args.capture, args.labels)

        def progress(stage: str, fraction: float) -> None:
            if not args.quiet:
                print(f"{stage} {fraction:.0%}", file=sys.stderr)

        result = take_inventory(
            capture,
            classes,
            {name: m.diameter_m for name, m in models.items()},
            models.__getitem__,
            options,
            progress,
        )
    except (InputError, json.JSONDecodeError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except PipelineError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 3
    text = json.dumps(result.to_json(), indent=2, default=float)
    if args.out:
        args.out.write_text(text + "\n")
    else:
        print(text)
    return 0
