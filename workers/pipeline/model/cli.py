"""``python -m workers.pipeline model``: prepare one library object from the command line."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from workers.pipeline.errors import InputError
from workers.pipeline.model.options import MODEL_PRESETS, UNITS_TO_M
from workers.pipeline.model.prepare import (
    prepare_model,
)
from workers.pipeline.model.symmetry_group import SymmetrySpec, spec_from_json


def cli(argv: list[str]) -> int:
    """``python -m workers.pipeline model MESH --out DIR [--units mm] [--symmetry JSON]``."""
    ap = argparse.ArgumentParser(prog="python -m workers.pipeline model")
    ap.add_argument("mesh", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--units", default="m", choices=sorted(UNITS_TO_M))
    ap.add_argument("--preset", default="default", choices=sorted(MODEL_PRESETS))
    ap.add_argument("--name", default=None)
    ap.add_argument("--symmetry", default="auto", help='"auto", "none" or a JSON spec')
    args = ap.parse_args(argv)
    spec: SymmetrySpec | None = None
    if args.symmetry != "auto":
        raw: Any = {"kind": "none"} if args.symmetry == "none" else json.loads(args.symmetry)
        spec = spec_from_json(raw)
    try:
        model = prepare_model(
            args.mesh, args.out, MODEL_PRESETS[args.preset], args.units, spec, name=args.name
        )
    except InputError as exc:
        print(exc)
        return 2
    s = dict(model.summary)
    s.pop("options", None)
    print(json.dumps(s, indent=2))
    return 0
