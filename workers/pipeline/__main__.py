"""Run one pipeline stage without the service: ``python -m workers.pipeline <stage> ...``.

Each stage module exposes ``cli(argv: list[str]) -> int``; this dispatcher imports only the
stage asked for, so a stage with heavy imports costs nothing to the others.
"""

from __future__ import annotations

import importlib
import sys

STAGES: dict[str, str] = {
    "synth": "workers.pipeline.synth.cli",
    "reconstruct": "workers.pipeline.reconstruct.cli",
    "scan": "workers.pipeline.scan.cli",
    "compare": "workers.pipeline.compare.cli",
    "pose": "workers.pipeline.pose.cli",
    "inventory": "workers.pipeline.inventory.cli",
    "model": "workers.pipeline.model.cli",
    "option-schema": "workers.pipeline.option_schema",
    "option-docs": "workers.pipeline.option_docs",
}


def main(argv: list[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in {"-h", "--help"} or args[0] not in STAGES:
        print("usage: python -m workers.pipeline <stage> [args...]\nstages: " + ", ".join(STAGES))
        return 0 if args and args[0] in {"-h", "--help"} else 2
    module = importlib.import_module(STAGES[args[0]])
    result: int = module.cli(args[1:])
    return result


if __name__ == "__main__":
    raise SystemExit(main())
