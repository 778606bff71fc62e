"""Fail when a function is too long or takes too many parameters.

``python .ci/function_size.py app workers`` lists every function (and method) over
``--max-lines`` lines (80; decorators not counted, the docstring counted) or with more than
``--max-params`` parameters (8; ``self`` and ``cls`` not counted, ``*args`` and ``**kwargs``
count one each), and exits 1 when there is any. ``make lint`` runs it.

A long function is split along its steps into named functions with typed inputs and outputs;
many parameters become a frozen dataclass. Standard library only, so it runs before the
project is installed.
"""

from __future__ import annotations

import argparse
import ast
import sys
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class Offender:
    """One function over a limit: where it is, its length in lines and its parameter count."""

    path: Path
    line: int
    name: str
    n_lines: int
    n_params: int


def _n_params(args: ast.arguments) -> int:
    """Parameters a caller can pass, without a leading ``self`` or ``cls``."""
    positional = [*args.posonlyargs, *args.args]
    n = len(positional) + len(args.kwonlyargs)
    n += (args.vararg is not None) + (args.kwarg is not None)
    if positional and positional[0].arg in ("self", "cls"):
        n -= 1
    return n


def offenders(paths: list[Path], max_lines: int, max_params: int) -> list[Offender]:
    """Every function under ``paths`` (files or folders of .py files) over either limit."""
    files = sorted(f for p in paths for f in ([p] if p.is_file() else p.rglob("*.py")))
    found: list[Offender] = []
    for file in files:
        tree = ast.parse(file.read_text(encoding="utf-8"), filename=str(file))
        for node in ast.walk(tree):
            if not isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                continue
            n_lines = (node.end_lineno or node.lineno) - node.lineno + 1
            n_params = _n_params(node.args)
            if n_lines > max_lines or n_params > max_params:
                found.append(Offender(file, node.lineno, node.name, n_lines, n_params))
    return found


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("paths", nargs="+", type=Path, help="files or folders to check")
    parser.add_argument("--max-lines", type=int, default=80)
    parser.add_argument("--max-params", type=int, default=8)
    args = parser.parse_args(argv)
    found = offenders(args.paths, args.max_lines, args.max_params)
    for o in sorted(found, key=lambda o: (str(o.path), o.line)):
        print(f"{o.path}:{o.line}: {o.name}: {o.n_lines} lines, {o.n_params} parameters")
    if found:
        print(
            f"{len(found)} function(s) over {args.max_lines} lines or {args.max_params} "
            "parameters: split them along their steps",
            file=sys.stderr,
        )
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
