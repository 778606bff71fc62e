"""Strict JSON for documents from outside: request bodies, cameras.json, the symmetry form
field.

Python's ``json`` accepts more than JSON and fails in ways no caller handles: ``NaN`` and
``Infinity`` (not JSON; PostgreSQL refuses to store them, SQLite silently stores null),
``1e400`` (parses to ``inf``), integers past 4,300 digits (``ValueError`` from the int-string
limit), nesting deep enough to exhaust the stack (``RecursionError``), and strings no
database stores (NUL characters, unpaired surrogates such as ``"\\ud800"``). :func:`loads`
turns each into :class:`InvalidInput` naming where it is (``options.compare.max_clusters``),
and bounds what passes: integers fit in 64 bits, floats are finite, nesting is at most
:data:`MAX_DEPTH` levels.
"""

from __future__ import annotations

import json
import math
from typing import Any

from app.core.errors import InvalidInput
from app.formats.errors import short
from app.formats.errors import show as show  # re-exported: the API names values with it

MAX_DEPTH = 32
"""The deepest nesting accepted; the deepest document the API defines (a marker pose in an
environment's reference) is 6 levels."""
INT_LIMIT = 2**63
_MAX_DIGITS = 19  # len(str(2**63)); anything longer is out of range without converting it


class _Rejected:
    """A number JSON cannot carry here, kept in place so its path can be named."""

    def __init__(self, why: str) -> None:
        self.why = why


def _parse_int(text: str) -> int | _Rejected:
    digits = len(text.lstrip("-"))
    if digits > _MAX_DIGITS:
        return _Rejected(f"an integer of {digits} digits is out of range (64-bit integers)")
    value = int(text)
    if not -INT_LIMIT <= value < INT_LIMIT:
        return _Rejected(f"{text} is out of range (64-bit integers)")
    return value


def _parse_float(text: str) -> float | _Rejected:
    value = float(text)
    if not math.isfinite(value):
        return _Rejected(f"{short(text)} is out of the range of a double")
    return value


def _parse_constant(name: str) -> _Rejected:
    return _Rejected(f"{name} is not a JSON number")


def path_join(where: str, key: str | int) -> str:
    """``where`` extended by a key (``.name`` or ``['odd key']``) or an index (``[3]``)."""
    if isinstance(key, int):
        return f"{where}[{key}]"
    if key.isidentifier() and key.isascii():
        return f"{where}.{key}" if where else key
    return f"{where}[{short(repr(key))}]"


def text_problem(text: str) -> str | None:
    """Why ``text`` cannot be stored (PostgreSQL refuses NUL in text and JSON; a lone
    surrogate such as "\\ud800" is not Unicode text and cannot be encoded as UTF-8)."""
    if "\x00" in text:
        return "text with a NUL character (\\u0000)"
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return "text with an unpaired surrogate (not Unicode)"
    return None


def _name(where: str, path: str) -> str:
    if not path:
        return where
    if where == "body" or path.startswith(where):
        return path
    return f"{where}: {path}"


def _find_rejected(doc: Any, where: str, root: str, code: str | None) -> None:
    """Walk ``doc`` (iteratively: it may be deep) for rejected numbers and excess depth."""
    stack: list[tuple[Any, str, int]] = [(doc, root, 0)]
    while stack:
        value, path, depth = stack.pop()
        if isinstance(value, _Rejected):
            raise InvalidInput(f"{_name(where, path)}: {value.why}", code=code)
        if isinstance(value, str) and (problem := text_problem(value)):
            raise InvalidInput(f"{_name(where, path)}: {problem}", code=code)
        if isinstance(value, dict | list):
            if depth >= MAX_DEPTH:
                raise InvalidInput(
                    f"{_name(where, path)}: nested more than {MAX_DEPTH} levels deep", code=code
                )
            if isinstance(value, dict):
                for key in value:
                    if problem := text_problem(key):
                        raise InvalidInput(
                            f"{_name(where, path_join(path, key))}: the key is {problem}",
                            code=code,
                        )
            items = value.items() if isinstance(value, dict) else enumerate(value)
            # Reversed, so the first problem in document order is the one reported.
            for key, item in reversed(list(items)):
                stack.append((item, path_join(path, key), depth + 1))


def loads(data: str | bytes, where: str, *, root: str = "", code: str | None = None) -> Any:
    """Parse ``data`` as strict JSON; :class:`InvalidInput` (with ``code`` when given) naming
    the document ``where`` ("body", "cameras.json") and the path inside it, which starts at
    ``root``: ``options.compare.max_clusters`` in a body, ``cameras.json: intrinsics.width``,
    ``symmetry.axis[0]`` with ``root`` "symmetry"."""
    try:
        text = data.decode("utf-8-sig") if isinstance(data, bytes) else data
    except UnicodeDecodeError as exc:
        raise InvalidInput(f"{where}: not UTF-8 text", code=code) from exc
    try:
        doc = json.loads(
            text,
            parse_int=_parse_int,
            parse_float=_parse_float,
            parse_constant=_parse_constant,
        )
    except json.JSONDecodeError as exc:
        raise InvalidInput(
            f"{where} line {exc.lineno} column {exc.colno}: not JSON ({exc.msg})", code=code
        ) from exc
    except RecursionError as exc:
        raise InvalidInput(f"{where}: nested more than {MAX_DEPTH} levels deep", code=code) from exc
    _find_rejected(doc, where, root, code)
    return doc
