"""docker-compose.yml is valid (Debian's docker-compose validates without an engine) and has
the production services with health checks."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest
import yaml

from app.core.settings import Settings
from tests.conftest import REPO_ROOT


def test_compose_file_is_valid(tmp_path: Path) -> None:
    """Valid once the required secrets are given (see .env.example)."""
    env_file = tmp_path / "test.env"
    env_file.write_text("".join(f"{k}={v}\n" for k, v in GOOD.items()))
    result = _compose(env_file, "-q")
    assert result.returncode == 0, result.stderr


def test_compose_services_and_health_checks() -> None:
    spec = yaml.safe_load((REPO_ROOT / "docker-compose.yml").read_text())
    services = spec["services"]
    assert {
        "postgres",
        "redis",
        "minio",
        "minio-bucket",
        "migrate",
        "api",
        "worker-cpu",
        "worker-webhooks",
    } <= set(services)
    for name in ("postgres", "redis", "minio", "api", "worker-cpu", "worker-webhooks"):
        assert "healthcheck" in services[name], name
    assert services["migrate"]["restart"] == "no"
    assert "-Q" in services["worker-cpu"]["command"] and "cpu" in services["worker-cpu"]["command"]


# --- secrets, limits and the data volume (field hardening) ----------------------------------

SECRET_VARS = (
    "POSTGRES_PASSWORD",
    "REDIS_PASSWORD",
    "TWINDELTA_SECRET_KEY",
    "TWINDELTA_BOOTSTRAP_ADMIN_KEY",
    "S3_ACCESS_KEY",
    "S3_SECRET_KEY",
)
APP_SERVICES = ("migrate", "api", "worker-cpu", "worker-webhooks", "worker-maintenance")


def _compose(env_file: Path, *args: str) -> subprocess.CompletedProcess[str]:
    """``docker-compose config`` with only ``env_file`` as the environment's source: the
    caller's shell and any ``.env`` in the checkout are kept out."""
    binary = shutil.which("docker-compose")
    if binary is None:
        pytest.fail("docker-compose is not installed: `make test` installs it (apt, as root)")
    env = {k: v for k, v in os.environ.items() if k not in SECRET_VARS and k != "PORT"}
    return subprocess.run(
        [binary, "--env-file", str(env_file), "-f", "docker-compose.yml", "config", *args],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        timeout=60,
        env=env,
    )


def _rendered(tmp_path: Path, values: dict[str, str]) -> dict[str, Any]:
    env_file = tmp_path / "test.env"
    env_file.write_text("".join(f"{k}={v}\n" for k, v in values.items()))
    result = _compose(env_file)
    assert result.returncode == 0, result.stderr
    rendered: dict[str, Any] = yaml.safe_load(result.stdout)
    return rendered


GOOD = {
    "POSTGRES_PASSWORD": "pg-5d1c0e7b9a4f4e2c",
    "REDIS_PASSWORD": "rd-8f2a6b3c1d0e4f5a",
    "TWINDELTA_SECRET_KEY": "5e0f9c2a7b41d86e3f1a0c9b8d7e6f5a",
    "TWINDELTA_BOOTSTRAP_ADMIN_KEY": "",
    "S3_ACCESS_KEY": "twindelta-s3",
    "S3_SECRET_KEY": "s3-9a8b7c6d5e4f3a2b",
}


def test_compose_refuses_to_render_without_passwords(tmp_path: Path) -> None:
    """No default database or Redis password or secret key: compose stops and names the
    missing one."""
    for missing in (
        "POSTGRES_PASSWORD",
        "REDIS_PASSWORD",
        "TWINDELTA_SECRET_KEY",
        "S3_ACCESS_KEY",
        "S3_SECRET_KEY",
    ):
        env_file = tmp_path / f"no-{missing}.env"
        env_file.write_text("".join(f"{k}={v}\n" for k, v in GOOD.items() if k != missing))
        result = _compose(env_file, "-q")
        assert result.returncode != 0, f"compose rendered without {missing}"
        assert missing in result.stderr


def test_compose_uses_the_given_passwords_everywhere(tmp_path: Path) -> None:
    spec = _rendered(tmp_path, GOOD)
    services = spec["services"]
    text = yaml.safe_dump(spec)
    assert ":twindelta@" not in text  # the old default database password
    assert services["postgres"]["environment"]["POSTGRES_PASSWORD"] == GOOD["POSTGRES_PASSWORD"]
    redis_command = " ".join(services["redis"]["command"])
    assert f"--requirepass {GOOD['REDIS_PASSWORD']}" in redis_command
    for name in APP_SERVICES:
        env = services[name]["environment"]
        assert f":{GOOD['POSTGRES_PASSWORD']}@postgres:5432/" in env["TWINDELTA_DATABASE_URL"]
        assert env["TWINDELTA_BROKER_URL"] == f"redis://:{GOOD['REDIS_PASSWORD']}@redis:6379/0"
        assert env["TWINDELTA_SECRET_KEY"] == GOOD["TWINDELTA_SECRET_KEY"]
        assert env["TWINDELTA_RETENTION_KEEP_LAST_SNAPSHOTS"] == "0"  # off unless set


def test_compose_services_have_memory_limits(tmp_path: Path) -> None:
    services = _rendered(tmp_path, GOOD)["services"]
    for name, service in services.items():
        assert service.get("mem_limit"), f"{name} has no memory limit"
    overridden = _rendered(tmp_path, {**GOOD, "WORKER_CPU_MEM_LIMIT": "3g"})["services"]
    assert str(overridden["worker-cpu"]["mem_limit"]).lower() in {"3g", str(3 * 1024**3)}


def test_compose_empty_bootstrap_key_is_not_fatal(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The environment compose gives the app with the file's default (an empty bootstrap
    key) is accepted by the settings, so ``migrate`` and everything after it start."""
    services = _rendered(tmp_path, GOOD)["services"]
    for name in APP_SERVICES:
        env = services[name]["environment"]
        assert env["TWINDELTA_BOOTSTRAP_ADMIN_KEY"] in ("", None)
        for key, value in env.items():
            monkeypatch.setenv(key, "" if value is None else str(value))
        settings = Settings()
        assert settings.bootstrap_admin_key is None


def test_env_example_renders_and_names_every_secret(tmp_path: Path) -> None:
    example = (REPO_ROOT / ".env.example").read_text()
    names = {
        line.split("=", 1)[0].strip()
        for line in example.splitlines()
        if "=" in line and not line.lstrip().startswith("#")
    }
    assert set(SECRET_VARS) <= names
    filled = tmp_path / "filled.env"
    filled.write_text(
        example.replace("POSTGRES_PASSWORD=", "POSTGRES_PASSWORD=a1b2c3d4e5f6a7b8")
        .replace("REDIS_PASSWORD=", "REDIS_PASSWORD=c1d2e3f4a5b6c7d8")
        .replace("TWINDELTA_SECRET_KEY=", f"TWINDELTA_SECRET_KEY={GOOD['TWINDELTA_SECRET_KEY']}")
        .replace("S3_ACCESS_KEY=", f"S3_ACCESS_KEY={GOOD['S3_ACCESS_KEY']}")
        .replace("S3_SECRET_KEY=", f"S3_SECRET_KEY={GOOD['S3_SECRET_KEY']}")
    )
    result = _compose(filled, "-q")
    assert result.returncode == 0, result.stderr
    assert ".env" in (REPO_ROOT / ".gitignore").read_text().split()


def test_dockerfile_creates_data_owned_by_the_runtime_user() -> None:
    """A named volume mounted at /data takes the image folder's owner on first use, so the
    image must create /data owned by the uid it runs as (1000); otherwise the API and the
    workers cannot write files, the SQLite file or the beat schedule there."""
    lines = [
        line.strip()
        for line in (REPO_ROOT / "Dockerfile").read_text().replace("\\\n", " ").splitlines()
    ]
    user_at = next(i for i, line in enumerate(lines) if line.startswith("USER "))
    assert lines[user_at].split()[1].split(":")[0] in {"1000", "twindelta"}
    setup = " ".join(line for line in lines[:user_at] if line.startswith("RUN "))
    assert "mkdir -p /data" in setup
    assert "chown 1000:1000 /data" in setup or "chown twindelta:twindelta /data" in setup
    spec = yaml.safe_load((REPO_ROOT / "docker-compose.yml").read_text())
    for name in APP_SERVICES:
        assert spec["services"][name]["environment"]["TWINDELTA_DATA_DIR"] == "/data"


def test_compose_app_containers_share_only_database_broker_and_bucket(tmp_path: Path) -> None:
    """Files go to the bucket; each app container's /data is a private anonymous volume
    (scratch), so no named volume is shared and workers can move to other hosts."""
    services = _rendered(tmp_path, GOOD)["services"]
    for name in APP_SERVICES:
        service = services[name]
        env = service["environment"]
        assert env["TWINDELTA_STORAGE_URL"] == "s3://twindelta"
        assert env["TWINDELTA_S3_ENDPOINT_URL"] == "http://minio:9000"
        assert env["AWS_ACCESS_KEY_ID"] == GOOD["S3_ACCESS_KEY"]
        assert env["AWS_SECRET_ACCESS_KEY"] == GOOD["S3_SECRET_KEY"]
        for volume in service.get("volumes", []):
            # compose v1 renders an anonymous volume as its bare container path
            assert volume == "/data", (name, volume)
    assert services["minio"]["environment"]["MINIO_ROOT_PASSWORD"] == GOOD["S3_SECRET_KEY"]
    for name in ("api", "worker-cpu"):
        depends = services[name]["depends_on"]
        assert depends["minio-bucket"]["condition"] == "service_completed_successfully"
