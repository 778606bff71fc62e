"""Fixtures shared by every tier of the suite."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
#: fixtures whose one set-up per session is minutes of work: their tests share a worker
SHARED_SCENE_FIXTURES = {"small_scene", "embedded_api"}


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """For pytest-xdist's ``--dist loadgroup`` (``make test``): a file's tests run on one
    worker (its module fixtures are set up once), the tests of :data:`SHARED_SCENE_FIXTURES`
    on one worker, and files with a ``slow`` test are handed out first so that no worker
    is left with a long test at the end."""
    for item in items:
        shared = SHARED_SCENE_FIXTURES & set(getattr(item, "fixturenames", ()))
        group = "shared_scene" if shared else item.nodeid.split("::")[0]
        item.add_marker(pytest.mark.xdist_group(group))
    slow_groups = {_group(i) for i in items if i.get_closest_marker("slow")}
    items.sort(key=lambda i: _group(i) not in slow_groups)


def _group(item: pytest.Item) -> str:
    marker = item.get_closest_marker("xdist_group")
    return str(marker.args[0]) if marker else ""


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The third-party data folder (``../shared/data`` beside the repository).

    Override with ``TWINDELTA_SHARED_DATA``. Fails, never skips, when it is missing: the
    real-data tests are part of the suite.
    """
    path = Path(os.environ.get("TWINDELTA_SHARED_DATA", REPO_ROOT.parent / "shared" / "data"))
    if not (path / "ycb").is_dir():
        pytest.fail(f"shared data not found at {path}; set TWINDELTA_SHARED_DATA")
    return path


@pytest.fixture(scope="session")
def s3_endpoint() -> Iterator[str]:
    """The endpoint of a loopback S3 emulator (moto) shared by the session."""
    from bench.loopback import start_s3_server  # moto takes a second to import

    endpoint_url, stop = start_s3_server()
    yield endpoint_url
    stop()


@pytest.fixture
def s3_storage_url(s3_endpoint: str, monkeypatch: pytest.MonkeyPatch) -> Iterator[tuple[str, str]]:
    """``(storage_url, endpoint_url)`` of a fresh bucket on the emulator, with the test
    credentials in this process's AWS environment (and no profile or config file)."""
    from bench.loopback import TEST_CREDENTIALS, create_bucket, drop_bucket

    for name, value in TEST_CREDENTIALS.items():
        monkeypatch.setenv(name, value)
    for name in ("AWS_SESSION_TOKEN", "AWS_PROFILE", "AWS_DEFAULT_PROFILE"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("AWS_CONFIG_FILE", os.devnull)
    monkeypatch.setenv("AWS_SHARED_CREDENTIALS_FILE", os.devnull)
    bucket = create_bucket(s3_endpoint)
    yield f"s3://{bucket}/twindelta", s3_endpoint
    drop_bucket(s3_endpoint, bucket)
