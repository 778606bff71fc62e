"""docs/options.md, written from the option classes themselves.

``python -m workers.pipeline option-docs --out docs/options.md`` lists, for every option
class, each field's name, type, default and one-line meaning, and each named preset's
differences from the default; ``make lint`` fails when the file is stale.

A field's meaning is the trailing ``# ...`` on its line. The comment lines directly above a
field (no blank line between) are a group heading when the field has a trailing comment;
otherwise a short first line followed by more lines (``# multi-view stereo``) is the heading
and the rest is the meaning, and a single line is the meaning. A field with no comment
shows "—". Nothing here is hand-written per option, so the
document cannot drift from the code.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import importlib
import inspect
import io
import textwrap
import tokenize
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any


@dataclass(frozen=True)
class OptionClass:
    """One documented option class: where it lives and how a user sets it.

    ``modules``: module paths tried in order (the first that imports is used);
    ``presets``: the name of the module's ``dict[str, Options]`` of presets, or "" for none.
    """

    title: str
    modules: tuple[str, ...]
    class_name: str
    presets: str
    how_set: str


@dataclass(frozen=True)
class FieldDoc:
    """One option as documented: heading of its group ("" for none) and its table row."""

    group: str
    name: str
    type_text: str
    default_text: str
    meaning: str


OPTION_CLASSES: tuple[OptionClass, ...] = (
    OptionClass(
        "Reconstruct",
        ("workers.pipeline.reconstruct.options",),
        "ReconstructOptions",
        "PRESETS",
        'An environment\'s `options.reconstruct` (`{"preset": ..., <option>: <value>}`), or '
        "`python -m workers.pipeline reconstruct --preset NAME --set KEY=VALUE`.",
    ),
    OptionClass(
        "Compare",
        ("workers.pipeline.compare.options",),
        "CompareOptions",
        "PRESETS",
        "An environment's `options.compare`, the body of "
        "`POST /v1/environments/{id}/comparisons`, or "
        "`python -m workers.pipeline compare --preset NAME --options JSON`.",
    ),
    OptionClass(
        "Threshold (`ThresholdSpec`)",
        ("workers.pipeline.compare.options",),
        "ThresholdSpec",
        "",
        'The compare options `threshold` and `grow_threshold`, e.g. `{"kind": "lod"}`.',
    ),
    OptionClass(
        "Pose",
        ("workers.pipeline.pose.options",),
        "PoseOptions",
        "POSE_PRESETS",
        "The `pose` key of the compare options (`options.compare.pose` of an environment, or "
        '`"pose"` in the body of `POST /v1/environments/{id}/comparisons`), '
        '`{"preset": ..., <option>: <value>}`; or '
        "`python -m workers.pipeline pose --preset NAME`.",
    ),
    OptionClass(
        "Inventory",
        ("workers.pipeline.inventory.options",),
        "InventoryOptions",
        "INVENTORY_PRESETS",
        'An environment\'s `options.inventory` (`{"preset": ..., <option>: <value>}`; '
        "`compare` holds overrides of the compare preset `compare_preset`, `pose` the pose "
        'options `{"preset": ..., <option>: <value>}`), used by every snapshot job of the '
        "environment; or `python -m workers.pipeline inventory CAPTURE --preset NAME "
        "--options JSON`.",
    ),
    OptionClass(
        "Model",
        ("workers.pipeline.model.options",),
        "ModelOptions",
        "MODEL_PRESETS",
        "Preparing a library object's model; `python -m workers.pipeline model --preset NAME`.",
    ),
    OptionClass(
        "Symmetry detection",
        ("workers.pipeline.model.options",),
        "SymmetryOptions",
        "",
        "The model options' `symmetry`: how a library object's symmetries are detected.",
    ),
)


def _import_first(modules: tuple[str, ...], attribute: str) -> types.ModuleType:
    """The first of ``modules`` that imports and defines ``attribute``; ImportError if none."""
    for name in modules:
        try:
            module = importlib.import_module(name)
        except ImportError:
            continue
        if hasattr(module, attribute):
            return module
    raise ImportError(f"none of {', '.join(modules)} defines {attribute}")


def type_text(hint: Any) -> str:
    """A field's type hint as a reader writes it: ``int``, ``float | null``, ``"a" | "b"``."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        return " | ".join("null" if a is type(None) else type_text(a) for a in args)
    if origin is typing.Literal:
        return " | ".join(f'"{a}"' if isinstance(a, str) else repr(a) for a in args)
    if origin is tuple:
        inner = type_text(args[0]) if args else "any"
        return f"list of {inner}"
    if origin in (Mapping, dict):
        return "object"
    if isinstance(hint, type):
        return hint.__name__
    return str(hint)


def value_text(value: Any) -> str:
    """A default or preset value as JSON-like text (tuples as lists, None as null)."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, tuple):
        return "[" + ", ".join(value_text(v) for v in value) + "]"
    if isinstance(value, Mapping):
        return "{" + ", ".join(f"{k}: {value_text(v)}" for k, v in value.items()) + "}"
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        to_json = getattr(value, "to_json", None)
        if callable(to_json):
            items = to_json().items()
            return "{" + ", ".join(f"{k}: {value_text(v)}" for k, v in items) + "}"
        return f"{type(value).__name__}()"
    return repr(value)


def _comments_by_line(source: str) -> dict[int, str]:
    """1-based line number → the text of the ``#`` comment on that line (without ``#``)."""
    comments: dict[int, str] = {}
    for token in tokenize.generate_tokens(io.StringIO(source).readline):
        if token.type == tokenize.COMMENT:
            comments[token.start[0]] = token.string.lstrip("#").strip()
    return comments


def _is_heading(block: list[str]) -> bool:
    """Whether the first line of a comment block names a group: short, no full stop, and
    followed by more comment lines."""
    first = block[0] if block else ""
    return len(block) > 1 and len(first.split()) <= 5 and not first.endswith((".", ":"))


def _split_block(block: list[str], trailing: list[str]) -> tuple[str | None, list[str]]:
    """(group heading or None when the block names none, meaning lines) of a field whose
    comment block above is ``block`` and whose trailing comments are ``trailing``."""
    if trailing:
        return (" ".join(block) if block else None), trailing
    if _is_heading(block):
        return block[0], block[1:]
    return None, block


def field_comments(cls: type) -> dict[str, tuple[str, str]]:
    """Field name → (group heading or "", meaning) from the comments in ``cls``'s source."""
    source = textwrap.dedent(inspect.getsource(cls))
    lines = source.splitlines()
    comments = _comments_by_line(source)
    out: dict[str, tuple[str, str]] = {}
    group = ""
    class_node = ast.parse(source).body[0]
    assert isinstance(class_node, ast.ClassDef)
    for node in class_node.body:
        if not (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)):
            continue
        name = node.target.id
        block: list[str] = []
        line = node.lineno - 1
        while line >= 1 and lines[line - 1].lstrip().startswith("#"):
            block.insert(0, comments.get(line, ""))
            line -= 1
        last = node.end_lineno or node.lineno
        trailing = [comments[n] for n in range(node.lineno, last + 1) if n in comments]
        heading, meaning = _split_block(block, trailing)
        group = group if heading is None else heading
        out[name] = (group, " ".join(part for part in meaning if part))
    return out


def field_docs(cls: type) -> list[FieldDoc]:
    """The documented fields of an option dataclass, in declaration order."""
    hints = typing.get_type_hints(cls)
    comments = field_comments(cls)
    docs: list[FieldDoc] = []
    for f in dataclasses.fields(cls):
        if f.default is not dataclasses.MISSING:
            default = f.default
        elif f.default_factory is not dataclasses.MISSING:
            default = f.default_factory()
        else:
            default = None
        group, meaning = comments.get(f.name, ("", ""))
        docs.append(FieldDoc(group, f.name, type_text(hints[f.name]), value_text(default), meaning))
    return docs


def preset_lines(presets: dict[str, Any]) -> list[str]:
    """One bullet per preset: the options where it differs from the class's defaults."""
    lines: list[str] = []
    for name, options in presets.items():
        base = type(options)()
        changed = [
            f"`{f.name}` {value_text(getattr(options, f.name))}"
            for f in dataclasses.fields(options)
            if f.name != "preset" and getattr(options, f.name) != getattr(base, f.name)
        ]
        lines.append(f"- `{name}`: " + (", ".join(changed) if changed else "the defaults"))
    return lines


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ") or "—"


def section(spec: OptionClass) -> list[str]:
    """The Markdown section of one option class."""
    module = _import_first(spec.modules, spec.class_name)
    cls = getattr(module, spec.class_name)
    doc = inspect.getdoc(cls) or ""
    out = [f"## {spec.title}", "", f"`{module.__name__}.{spec.class_name}`. {spec.how_set}", ""]
    if doc:
        out += [doc, ""]
    if spec.presets:
        out += ["Presets:", "", *preset_lines(getattr(module, spec.presets)), ""]
    group = None
    for f in field_docs(cls):
        if f.group != group:
            group = f.group
            out += ([f"### {group}", ""] if group else []) + [
                "| option | type | default | meaning |",
                "|---|---|---|---|",
            ]
        row = [f"`{f.name}`", _cell(f.type_text), f"`{f.default_text}`", _cell(f.meaning)]
        out.append("| " + " | ".join(row) + " |")
    return [*_close_tables(out), ""]


def _close_tables(lines: list[str]) -> list[str]:
    """Insert a blank line before each ``###`` heading that follows a table row."""
    out: list[str] = []
    for line in lines:
        if line.startswith("### ") and out and out[-1].startswith("|"):
            out.append("")
        out.append(line)
    return out


def option_docs() -> str:
    """The whole of docs/options.md."""
    head = [
        "# Options",
        "",
        "Generated by `make option-docs` (`python -m workers.pipeline option-docs`) from the",
        "option classes in `workers/pipeline/`; do not edit by hand: change the field's comment",
        "instead. Lengths are in metres and angles in degrees unless a name says",
        "otherwise. A job stores its preset name and overrides, so every result can be",
        "re-run with the same options. Why an option has its value, and the measurements",
        "behind it, are in `bench/README.md` and `docs/decisions/`.",
        "",
    ]
    body = [line for spec in OPTION_CLASSES for line in section(spec)]
    return "\n".join(head + body).rstrip("\n") + "\n"


def cli(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m workers.pipeline option-docs")
    parser.add_argument("--out", type=Path, help="write here (default: standard output)")
    args = parser.parse_args(argv)
    text = option_docs()
    if args.out:
        args.out.write_text(text, encoding="utf-8")
    else:
        print(text, end="")
    return 0
