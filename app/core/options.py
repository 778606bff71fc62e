"""Pipeline options as posted with an environment or a comparison, checked against the
names, presets and types in ``option_schema.json`` (written from the workers' option classes
by ``make option-schema``), so a bad option is a 422 when it is posted, not a failed job later.

What only the stage itself can judge (a value's range, e.g. ``max_clusters: 0``) is still a
job error with the stage's message.
"""

from __future__ import annotations

import json
import math
from functools import cache
from pathlib import Path
from typing import Any

from app.core.errors import InvalidInput
from app.core.jsondoc import INT_LIMIT, show

SCHEMA_PATH = Path(__file__).with_name("option_schema.json")
STAGES = ("reconstruct", "compare", "inventory")
#: a stage's options may hold another's under its name: the comparison job poses what it
#: found, so the compare options carry the pose options as ``"pose": {...}``
NESTED_STAGES: dict[str, str] = {"compare": "pose"}


@cache
def schema() -> dict[str, Any]:
    """The parsed ``option_schema.json``."""
    loaded: dict[str, Any] = json.loads(SCHEMA_PATH.read_text())
    return loaded


def check_environment_options(options: Any) -> dict[str, Any]:
    """An environment's ``options`` ({"reconstruct": {...}, "compare": {...}, "inventory":
    {...}, "retention": {...}}, each optional; a stage's a preset name under "preset" and
    option overrides); InvalidInput naming the first thing wrong."""
    if options is None:
        return {}
    if not isinstance(options, dict):
        raise InvalidInput(f"options must be an object, got {show(options)}")
    sections = (*STAGES, "retention")
    unknown = sorted(set(options) - set(sections))
    if unknown:
        raise InvalidInput(
            f"unknown options section(s) {', '.join(unknown)}; known: {', '.join(sections)}"
        )
    return {
        stage: (
            check_retention_options(value, f"options.{stage}")
            if stage == "retention"
            else check_stage_options(stage, value, f"options.{stage}")
        )
        for stage, value in options.items()
    }


# name: (whole numbers only, largest value, what it is); 36,500 days is a century
RETENTION_OPTIONS: dict[str, tuple[bool, int, str]] = {
    "images_after_days": (False, 36_500, "a number of days"),
    "keep_last_snapshots": (True, INT_LIMIT, "a whole number"),
}


def check_retention_options(options: Any, where: str = "options.retention") -> dict[str, Any]:
    """An environment's retention policy, overriding the settings' for it (app/core/retention):
    ``images_after_days`` (a number of days, 0: keep the photos) and ``keep_last_snapshots``
    (a whole number, 0: keep every snapshot), each optional and at least 0."""
    if options is None:
        return {}
    if not isinstance(options, dict):
        raise InvalidInput(f"{where} must be an object, got {show(options)}")
    for name, value in options.items():
        spec = RETENTION_OPTIONS.get(name)
        if spec is None:
            raise InvalidInput(
                f"{where}: unknown option {show(name)}; known: {', '.join(RETENTION_OPTIONS)}"
            )
        whole, largest, what = spec
        if (
            isinstance(value, bool)
            or not isinstance(value, int if whole else int | float)
            or not math.isfinite(value)
            or not 0 <= value <= largest
        ):
            raise InvalidInput(f"{where}.{name}: {what} from 0 to {largest}, got {show(value)}")
    return dict(options)


def check_stage_options(
    stage: str, options: Any, where: str = "options", *, overrides_only: bool = False
) -> dict[str, Any]:
    """One stage's options (``stage`` "reconstruct", "compare", "pose" or "inventory"; the
    compare options may nest the pose options under ``"pose"``, the inventory options hold
    compare overrides under ``"compare"`` and pose options under ``"pose"``), as given;
    ``overrides_only``: options of a preset named elsewhere, so no ``"preset"`` and no
    nested stage. InvalidInput naming ``where`` and the option for an unknown preset or
    option or a value of the wrong JSON type."""
    if options is None:
        return {}
    if not isinstance(options, dict):
        raise InvalidInput(f"{where} must be an object, got {show(options)}")
    spec = schema()[stage]
    if "preset" in options and options["preset"] not in spec["presets"]:
        raise InvalidInput(
            f"{where}.preset: unknown {stage} preset {show(options['preset'])}; "
            f"known: {', '.join(spec['presets'])}"
        )
    nested = None if overrides_only else NESTED_STAGES.get(stage)
    own = set(spec["options"]) | ({"preset"} if not overrides_only else set())
    unknown = sorted(set(options) - own - {nested})
    if unknown:
        hint = "; the preset is named beside them" if "preset" in unknown else ""
        raise InvalidInput(f"{where}: unknown {stage} option(s) {', '.join(unknown)}{hint}")
    for name, value in options.items():
        if name == nested:
            check_stage_options(name, value, f"{where}.{name}")
        elif name != "preset":
            _check_value(f"{where}.{name}", value, spec["options"][name])
    return dict(options)


def _number(value: Any) -> bool:
    """A JSON number the workers can use: not a bool, an int within 64 bits (10**400 would
    overflow float()), a finite float."""
    if isinstance(value, bool):
        return False
    if isinstance(value, int):
        return -INT_LIMIT <= value < INT_LIMIT
    return isinstance(value, float) and math.isfinite(value)


def _check_value(where: str, value: Any, kind: dict[str, Any]) -> None:
    """InvalidInput unless ``value`` fits ``kind`` (an entry of the schema)."""
    if value is None and kind.get("nullable"):
        return
    t = kind["type"]
    if t == "options":
        check_stage_options(kind["stage"], value, where, overrides_only=not kind["preset"])
        return
    if t == "threshold":
        _check_threshold(where, value)
        return
    if t == "float_list" and isinstance(value, list):
        for i, item in enumerate(value):
            if not _number(item):
                raise InvalidInput(f"{where}[{i}] must be a finite number, got {show(item)}")
        return
    ok = {
        "bool": isinstance(value, bool),
        "int": _number(value) and float(value).is_integer(),
        "float": _number(value),
        "str": isinstance(value, str),
        "float_list": False,
    }[t]
    if not ok:
        expected = {
            "float_list": "a list of numbers",
            "int": "an integer (64-bit)",
            "float": "a finite number",
        }.get(t, f"a {t}")
        raise InvalidInput(f"{where} must be {expected}, got {show(value)}")
    if "choices" in kind and value not in kind["choices"]:
        raise InvalidInput(
            f"{where} must be one of {', '.join(kind['choices'])}, got {show(value)}"
        )


def _check_threshold(where: str, value: Any) -> None:
    """A threshold in its JSON form, e.g. {"kind": "mean_std", "k": 1.0}."""
    if not isinstance(value, dict):
        raise InvalidInput(f"{where} must be an object such as {{'kind': 'mean_std', 'k': 1.0}}")
    keys = schema()["threshold"]
    unknown = sorted(set(value) - set(keys))
    if unknown:
        raise InvalidInput(f"{where}: unknown threshold key(s) {', '.join(unknown)}")
    for name, v in value.items():
        _check_value(f"{where}.{name}", v, keys[name])
