"""JSON Patch (RFC 6902, with JSON Pointer, RFC 6901) and JSON Merge Patch (RFC 7396) written
from the RFCs' text, independent of the code under test, plus a JSON Schema of a JSON Patch
document. ``test_rfc_patches.py`` checks them against the RFCs' own appendix examples.

No JSON Patch library is in the project's environment; these are the oracles that prove an
adapter body applies, not a copy of the code that builds it."""

from __future__ import annotations

import copy
from typing import Any


class PatchError(Exception):
    """The patch cannot be applied (RFC 6902 §5: the whole patch then fails)."""


def _tokens(pointer: str) -> list[str]:
    """RFC 6901 §3-4: "" is the whole document; otherwise "/"-separated, ~1 → "/", ~0 → "~"."""
    if pointer == "":
        return []
    if not pointer.startswith("/"):
        raise PatchError(f"pointer {pointer!r} does not start with '/'")
    return [t.replace("~1", "/").replace("~0", "~") for t in pointer[1:].split("/")]


def _index(container: list[Any], token: str, *, for_add: bool) -> int:
    if token == "-" and for_add:
        return len(container)
    if not token.isdigit() or (token != "0" and token.startswith("0")):
        raise PatchError(f"bad array index {token!r}")
    i = int(token)
    if i > len(container) or (i == len(container) and not for_add):
        raise PatchError(f"array index {i} out of range")
    return i


def _parent(doc: Any, tokens: list[str]) -> Any:
    node = doc
    for token in tokens[:-1]:
        if isinstance(node, dict):
            if token not in node:
                raise PatchError(f"member {token!r} does not exist")
            node = node[token]
        elif isinstance(node, list):
            node = node[_index(node, token, for_add=False)]
        else:
            raise PatchError(f"cannot descend into {node!r}")
    return node


def _get(doc: Any, pointer: str) -> Any:
    tokens = _tokens(pointer)
    if not tokens:
        return doc
    parent, last = _parent(doc, tokens), tokens[-1]
    if isinstance(parent, dict):
        if last not in parent:
            raise PatchError(f"{pointer} does not exist")
        return parent[last]
    if isinstance(parent, list):
        return parent[_index(parent, last, for_add=False)]
    raise PatchError(f"{pointer} does not exist")


def _add(doc: Any, pointer: str, value: Any) -> Any:
    """§4.1: the target's parent must exist; an object member is added or replaced; an array
    element is inserted (``-`` appends)."""
    tokens = _tokens(pointer)
    if not tokens:
        return value
    parent, last = _parent(doc, tokens), tokens[-1]
    if isinstance(parent, dict):
        parent[last] = value
    elif isinstance(parent, list):
        parent.insert(_index(parent, last, for_add=True), value)
    else:
        raise PatchError(f"the parent of {pointer} is not a container")
    return doc


def _remove(doc: Any, pointer: str) -> Any:
    """§4.2: the target must exist."""
    tokens = _tokens(pointer)
    if not tokens:
        raise PatchError("cannot remove the whole document")
    parent, last = _parent(doc, tokens), tokens[-1]
    if isinstance(parent, dict):
        if last not in parent:
            raise PatchError(f"{pointer} does not exist")
        del parent[last]
    elif isinstance(parent, list):
        del parent[_index(parent, last, for_add=False)]
    else:
        raise PatchError(f"{pointer} does not exist")
    return doc


def _equal(a: Any, b: Any) -> bool:
    """§4.6: numbers by value, objects regardless of member order, arrays element-wise."""
    if isinstance(a, bool) or isinstance(b, bool):
        return type(a) is type(b) and a == b
    if isinstance(a, int | float) and isinstance(b, int | float):
        return a == b
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_equal(a[k], b[k]) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_equal(x, y) for x, y in zip(a, b, strict=True))
    return type(a) is type(b) and a == b


def apply_json_patch(document: Any, patch: list[dict[str, Any]]) -> Any:
    """RFC 6902: apply ``patch``'s operations in order to a copy of ``document``; raises
    :class:`PatchError` if any operation fails (the document is then left as it was)."""
    doc = copy.deepcopy(document)
    for op in patch:
        kind, path = op.get("op"), op.get("path")
        if not isinstance(path, str):
            raise PatchError(f"operation {op!r} has no path")
        if kind == "add":
            doc = _add(doc, path, copy.deepcopy(op["value"]))
        elif kind == "remove":
            doc = _remove(doc, path)
        elif kind == "replace":
            _get(doc, path)  # §4.3: the target must exist
            doc = (
                _add(_remove(doc, path), path, copy.deepcopy(op["value"])) if path else op["value"]
            )
        elif kind == "move":
            if path.startswith(op["from"] + "/"):
                raise PatchError("cannot move a value into one of its children")
            value = _get(doc, op["from"])
            doc = _add(_remove(doc, op["from"]), path, value)
        elif kind == "copy":
            doc = _add(doc, path, copy.deepcopy(_get(doc, op["from"])))
        elif kind == "test":
            if not _equal(_get(doc, path), op["value"]):
                raise PatchError(f"test at {path} failed")
        else:
            raise PatchError(f"unknown op {kind!r}")
    return doc


def apply_merge_patch(target: Any, patch: Any) -> Any:
    """RFC 7396 §2, MergePatch(Target, Patch), on a copy of ``target``."""
    if not isinstance(patch, dict):
        return copy.deepcopy(patch)
    out = copy.deepcopy(target) if isinstance(target, dict) else {}
    for name, value in patch.items():
        if value is None:
            out.pop(name, None)
        else:
            out[name] = apply_merge_patch(out.get(name), value)
    return out


_POINTER = "^(/([^/~]|~[01])*)*$"
# RFC 6902 §3-4 as a JSON Schema: an array of operation objects, each with the members its
# op requires ("value" may be any JSON value, null included).
JSON_PATCH_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "type": "array",
    "items": {
        "type": "object",
        "required": ["op", "path"],
        "properties": {
            "op": {"enum": ["add", "remove", "replace", "move", "copy", "test"]},
            "path": {"type": "string", "pattern": _POINTER},
            "from": {"type": "string", "pattern": _POINTER},
        },
        "allOf": [
            {
                "if": {"properties": {"op": {"enum": ["add", "replace", "test"]}}},
                "then": {"required": ["value"]},
            },
            {
                "if": {"properties": {"op": {"enum": ["move", "copy"]}}},
                "then": {"required": ["from"]},
            },
        ],
    },
}
