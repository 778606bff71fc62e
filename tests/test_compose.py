"""docker-compose.yml is valid (Debian's docker-compose validates without an engine) and has
the production services with health checks."""

from __future__ import annotations

import shutil
import subprocess

import pytest
import yaml

from tests.conftest import REPO_ROOT


def test_compose_file_is_valid() -> None:
    binary = shutil.which("docker-compose")
    if binary is None:
        pytest.fail("docker-compose is not installed: `make test` installs it (apt, as root)")
    result = subprocess.run(
        [binary, "-f", "docker-compose.yml", "config", "-q"],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 0, result.stderr


def test_compose_services_and_health_checks() -> None:
    spec = yaml.safe_load((REPO_ROOT / "docker-compose.yml").read_text())
    services = spec["services"]
    assert {"postgres", "redis", "migrate", "api", "worker-cpu", "worker-webhooks"} <= set(services)
    for name in ("postgres", "redis", "api", "worker-cpu", "worker-webhooks"):
        assert "healthcheck" in services[name], name
    assert services["migrate"]["restart"] == "no"
    assert "-Q" in services["worker-cpu"]["command"] and "cpu" in services["worker-cpu"]["command"]
