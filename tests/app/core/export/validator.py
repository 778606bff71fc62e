"""The Khronos glTF validator (``tools/gltf-validator``, npm package ``gltf-validator``) run
on a ``.glb`` file: its JSON report. The tests fail, never skip, when it is not installed
(``make test-tools`` installs it)."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest

from tests.conftest import REPO_ROOT

TOOL = REPO_ROOT / "tools" / "gltf-validator"


def validate(glb: Path) -> dict[str, Any]:
    """The validator's report on ``glb`` (``report["issues"]`` has ``numErrors``,
    ``numWarnings`` and the ``messages``)."""
    node = shutil.which("node")
    if node is None or not (TOOL / "node_modules" / "gltf-validator").is_dir():
        pytest.fail("the glTF validator is not installed: run `make test-tools`")
    done = subprocess.run(
        [node, str(TOOL / "validate.mjs"), str(glb)],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    report: dict[str, Any] = json.loads(done.stdout)
    return report


def assert_valid(glb: Path) -> dict[str, Any]:
    """The report, after checking it has no error and no warning (messages shown if so)."""
    report = validate(glb)
    issues = report["issues"]
    assert (issues["numErrors"], issues["numWarnings"]) == (0, 0), issues["messages"]
    return report
