"""Fixtures shared by every tier of the suite."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]


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
