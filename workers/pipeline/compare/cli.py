"""``python -m workers.pipeline compare BEFORE_DIR AFTER_DIR [options]``.

Reads two capture folders (see files.py; a ``reconstruct`` output folder is one, with
``--before-labels``/``--after-labels`` and ``--classes`` pointing at the captures' YOLO
files; the photos are read from ``images/`` beside each labels folder when it is there),
compares them and writes the comparison JSON
(docs/contract.md "A comparison", without the service's ids) to ``--out`` or stdout, and the
changed points of each cluster to ``--clusters-dir`` as ``cluster_<id>_<side>.npy`` when
asked. Exit codes: 0 ok, 2 bad input, 3 comparison failed.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from workers.pipeline.compare.files import load_capture, load_classes, load_twin
from workers.pipeline.compare.options import PRESETS, options_from_json
from workers.pipeline.compare.stage import compare_snapshots
from workers.pipeline.errors import InputError, PipelineError


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m workers.pipeline compare", description=__doc__)
    p.add_argument("before", type=Path, help="capture folder of the earlier snapshot")
    p.add_argument("after", type=Path, help="capture folder of the later snapshot")
    p.add_argument("--classes", type=Path, help="classes.txt (default: AFTER/classes.txt)")
    p.add_argument("--before-labels", type=Path, help="YOLO labels (default: BEFORE/labels)")
    p.add_argument("--after-labels", type=Path, help="YOLO labels (default: AFTER/labels)")
    p.add_argument("--diameters", type=Path, help='JSON {"class": diameter_m}')
    p.add_argument("--twin", type=Path, help="twin state JSON (list of instances)")
    p.add_argument("--preset", default="default", choices=sorted(PRESETS))
    p.add_argument("--options", default="{}", help="JSON overrides of the preset")
    p.add_argument("--out", type=Path, help="write the comparison JSON here (default stdout)")
    p.add_argument("--clusters-dir", type=Path, help="write each cluster's points (.npy)")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    return p


def cli(argv: list[str]) -> int:
    """Run the compare stage from the command line; returns the exit code."""
    args = _parser().parse_args(argv)
    try:
        classes_path = args.classes or next(
            (d / "classes.txt" for d in (args.after, args.before) if (d / "classes.txt").is_file()),
            None,
        )
        if classes_path is None:
            raise InputError("no classes.txt in the capture folders; pass --classes")
        classes = load_classes(classes_path)
        diameters: dict[str, float] = {}
        if args.diameters:
            diameters = {
                str(k): float(v) for k, v in json.loads(args.diameters.read_text()).items()
            }
        twin = load_twin(args.twin) if args.twin else []
        options = options_from_json(args.preset, json.loads(args.options))
        before = load_capture(args.before, args.before_labels)
        after = load_capture(args.after, args.after_labels)

        def progress(stage: str, fraction: float) -> None:
            if not args.quiet:
                print(f"{stage} {fraction:.0%}", file=sys.stderr)

        result = compare_snapshots(before, after, twin, classes, diameters, options, progress)
    except (InputError, json.JSONDecodeError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except PipelineError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 3
    text = json.dumps(result.to_json(), indent=2)
    if args.out:
        args.out.write_text(text + "\n")
    else:
        print(text)
    if args.clusters_dir:
        args.clusters_dir.mkdir(parents=True, exist_ok=True)
        for c in result.clusters:
            np.save(args.clusters_dir / f"cluster_{c.id}_{c.side}.npy", c.points_env)
    return 0
