"""The names, presets and JSON types of the reconstruct, compare, pose and inventory options,
for the API.

The API may not import the workers (docs/architecture.md), yet it should refuse an environment or
comparison whose options a job would refuse, when they are posted rather than when the job
runs. ``python -m workers.pipeline option-schema --out app/core/option_schema.json`` writes
this description where ``app.core.options`` reads it; ``make lint`` fails when it is stale.

Each option is ``{"type": T}`` with T one of bool, int, float, str, float_list, threshold
(a ThresholdSpec in its JSON form, checked against ``"threshold"``), plus ``"nullable":
true`` when it may be null and ``"choices"`` for a closed set of strings, or ``{"type":
"options", "stage": S, "preset": P}`` for a field that holds stage S's options (P: whether
they may name their own ``"preset"``; else they are overrides of a preset named elsewhere).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import types
import typing
from pathlib import Path
from typing import Any

from workers.pipeline.compare.options import PRESETS as COMPARE_PRESETS
from workers.pipeline.compare.options import CompareOptions, ThresholdSpec
from workers.pipeline.inventory.options import INVENTORY_PRESETS, InventoryOptions
from workers.pipeline.pose.options import POSE_PRESETS, PoseOptions
from workers.pipeline.reconstruct.options import PRESETS as RECONSTRUCT_PRESETS
from workers.pipeline.reconstruct.options import ReconstructOptions

_SCALARS = {bool: "bool", int: "int", float: "float", str: "str"}
#: fields whose type hint does not say what they hold: another stage's options, or a preset
#: name of another stage. Add a row when an option class gains such a field.
_SPECIAL: dict[tuple[type, str], dict[str, Any]] = {
    (InventoryOptions, "compare_preset"): {"type": "str", "choices": sorted(COMPARE_PRESETS)},
    (InventoryOptions, "compare"): {"type": "options", "stage": "compare", "preset": False},
    (InventoryOptions, "pose"): {"type": "options", "stage": "pose", "preset": True},
}


def _option_type(hint: Any) -> dict[str, Any]:
    """The JSON description of one dataclass field's type hint; TypeError when it has none."""
    args = typing.get_args(hint)
    if typing.get_origin(hint) in (typing.Union, types.UnionType) and type(None) in args:
        rest = [a for a in args if a is not type(None)]
        if len(rest) == 1:
            return {**_option_type(rest[0]), "nullable": True}
    if hint in _SCALARS:
        return {"type": _SCALARS[hint]}
    if hint is ThresholdSpec:
        return {"type": "threshold"}
    if typing.get_origin(hint) is typing.Literal and all(isinstance(a, str) for a in args):
        return {"type": "str", "choices": list(args)}
    if typing.get_origin(hint) is tuple and args in ((float, ...),):
        return {"type": "float_list"}
    raise TypeError(f"no JSON description for option type {hint!r}")


def _options(cls: type) -> dict[str, dict[str, Any]]:
    hints = typing.get_type_hints(cls)
    return {
        f.name: _SPECIAL.get((cls, f.name)) or _option_type(hints[f.name])
        for f in dataclasses.fields(cls)
    }


def option_schema() -> dict[str, Any]:
    """{"reconstruct": {"presets", "options"}, "compare": {...}, "pose": {...},
    "inventory": {...}, "threshold": {...}}; the pose options are the ``pose`` key of the
    compare options."""
    return {
        "reconstruct": {
            "presets": sorted(RECONSTRUCT_PRESETS),
            "options": _options(ReconstructOptions),
        },
        "compare": {"presets": sorted(COMPARE_PRESETS), "options": _options(CompareOptions)},
        "pose": {"presets": sorted(POSE_PRESETS), "options": _options(PoseOptions)},
        "inventory": {
            "presets": sorted(INVENTORY_PRESETS),
            "options": _options(InventoryOptions),
        },
        "threshold": _options(ThresholdSpec),
    }


def cli(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m workers.pipeline option-schema")
    parser.add_argument("--out", type=Path, help="write here (default: standard output)")
    args = parser.parse_args(argv)
    text = json.dumps(option_schema(), indent=1, sort_keys=True) + "\n"
    if args.out:
        args.out.write_text(text)
    else:
        print(text, end="")
    return 0
