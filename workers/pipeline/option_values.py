"""The one way a stage's options are made from a preset name and JSON overrides.

Every stage (reconstruct, compare, pose) keeps its options as a frozen dataclass with named
presets; a job row stores the preset name and the overrides. :func:`with_overrides` applies
them, checking each value against its field's type hint: bool, int (a whole float is taken),
float (an int is taken), str, a ``Literal`` of strings (one of them), ``tuple[float, ...]``
(a list of numbers), ``X | None`` (null or an X), and a nested options dataclass with a
``from_json`` class method (its JSON object, or an instance). Anything else is an
InputError naming the stage and the option, never a job that fails later on a wrong type.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from collections.abc import Mapping
from typing import Any, Literal, TypeVar

from workers.pipeline.errors import InputError

T = TypeVar("T")
_SCALARS: tuple[type, ...] = (bool, int, float, str)


def with_overrides(stage: str, presets: Mapping[str, T], preset: str, overrides: Any) -> T:
    """``presets[preset]`` with ``overrides`` (a mapping of option name to JSON value)
    applied; InputError for an unknown preset, an unknown option or a value of another
    type, naming it."""
    if preset not in presets:
        raise InputError(f"unknown {stage} preset {preset!r}; known: {', '.join(sorted(presets))}")
    if overrides is None:
        overrides = {}
    if not isinstance(overrides, Mapping):
        raise InputError(f"{stage} options must be an object of option names, got {overrides!r}")
    base = presets[preset]
    hints = typing.get_type_hints(type(base))
    fields = {f.name for f in dataclasses.fields(base)}  # type: ignore[arg-type]
    unknown = sorted(set(overrides) - fields)
    if unknown:
        raise InputError(f"unknown {stage} options: {', '.join(unknown)}")
    values = {k: _value(f"{stage} option {k}", v, hints[k]) for k, v in overrides.items()}
    return dataclasses.replace(base, **values)  # type: ignore[type-var]


def _value(where: str, value: Any, hint: Any) -> Any:
    """``value`` as type ``hint``; InputError naming ``where`` when it is not one."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType) and type(None) in args:
        rest = [a for a in args if a is not type(None)]
        return None if value is None else _value(where, value, rest[0])
    if origin is Literal:
        if value in args:
            return value
        raise InputError(f"{where} must be one of {', '.join(map(str, args))}, got {value!r}")
    if origin is tuple:
        if isinstance(value, list | tuple) and all(_is_number(v) for v in value):
            return tuple(float(v) for v in value)
        raise InputError(f"{where} must be a list of numbers, got {value!r}")
    if hint in _SCALARS:
        return _scalar(where, value, hint)
    if isinstance(hint, type) and dataclasses.is_dataclass(hint) and hasattr(hint, "from_json"):
        if isinstance(value, hint):
            return value
        if isinstance(value, Mapping):
            return hint.from_json(value)
        raise InputError(f"{where} must be an object, got {value!r}")
    raise TypeError(f"{where}: no rule for option type {hint!r}")


def _scalar(where: str, value: Any, kind: type) -> Any:
    if kind is bool and isinstance(value, bool):
        return value
    if kind is int and _is_number(value) and float(value).is_integer():
        return int(value)
    if kind is float and _is_number(value):
        return float(value)
    if kind is str and isinstance(value, str):
        return value
    raise InputError(f"{where} must be of type {kind.__name__}, got {value!r}")


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)
