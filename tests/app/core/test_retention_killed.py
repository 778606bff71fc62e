"""What really killed processes leave behind, and the cleanup that removes it: an upload
process killed (SIGKILL) while it streams into its staging folder, and a worker killed
while it computes in its ``.work/<job>`` folder. The processes are real; the database is
an SQLite file they share with the test."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from datetime import timedelta
from pathlib import Path

import pytest
from sqlalchemy.orm import Session, sessionmaker

from app.core import db, environments, jobs, retention
from app.core.enums import JobKind, JobState
from app.core.models import Job, utcnow
from app.core.settings import Settings
from app.core.storage import LocalStorage
from tests.app.conftest import migrate
from tests.conftest import REPO_ROOT

UPLOAD = """
import os, sys
from app.core import db, ingest
from app.core.settings import get_settings
from app.core.storage import LocalStorage
settings = get_settings()
r, w = os.pipe()
os.write(w, b"\\xff\\xd8\\xff\\xe0" + b"\\0" * 1000)  # a photo that never finishes arriving
part = ingest.UploadPart("a.jpg", os.fdopen(r, "rb", buffering=0))
with db.transaction() as session:
    storage = LocalStorage(settings.resolved_storage_dir)
    files = ingest.UploadFiles(images=[part])
    ingest.create_snapshot(session, storage, settings, sys.argv[1], files)
"""

WORKER = """
import sys, time
from workers.runner import run_job
run_job(sys.argv[1], lambda ctx: time.sleep(600), lambda session, ctx, result: None)
"""


@pytest.fixture
def service(tmp_path: Path) -> Iterator[tuple[sessionmaker[Session], dict[str, str]]]:
    url = f"sqlite:///{tmp_path / 'twindelta.db'}"
    migrate(url)
    engine = db.make_engine(url)
    env = {
        **os.environ,
        "TWINDELTA_DATA_DIR": str(tmp_path),
        "TWINDELTA_DATABASE_URL": url,
        "PYTHONPATH": str(REPO_ROOT),
    }
    env.pop("TWINDELTA_BROKER_URL", None)
    env.pop("TWINDELTA_STORAGE_DIR", None)
    yield sessionmaker(bind=engine, expire_on_commit=False), env
    engine.dispose()


def _kill_when(
    script: str, arg: str, env: dict[str, str], ready: Callable[[], bool], timeout_s: float = 60
) -> None:
    """Run ``script`` in a new Python process, SIGKILL it once ``ready()`` holds."""
    proc = subprocess.Popen(
        [sys.executable, "-c", script, arg],
        env=env,
        cwd=REPO_ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    try:
        deadline = time.monotonic() + timeout_s
        while not ready():
            if proc.poll() is not None:
                out = proc.stdout.read().decode() if proc.stdout else ""
                pytest.fail(f"the process ended by itself ({proc.returncode}): {out[-2000:]}")
            if time.monotonic() > deadline:
                pytest.fail("the process never got there")
            time.sleep(0.05)
        proc.send_signal(signal.SIGKILL)
        assert proc.wait(timeout=30) == -signal.SIGKILL
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_staging_of_a_killed_upload_is_removed(
    tmp_path: Path, service: tuple[sessionmaker[Session], dict[str, str]]
) -> None:
    factory, env = service
    with factory.begin() as s:
        env_id = environments.create(s, "hall", ["bowl"], None, None).id
    staging = tmp_path / "files" / ".tmp"
    _kill_when(UPLOAD, env_id, env, lambda: any(staging.glob("*/images/a.jpg")))
    assert any(staging.glob("*/images/a.jpg"))  # left behind by the killed process
    storage = LocalStorage(tmp_path / "files")
    with factory.begin() as s:
        counts = retention.cleanup_files(s, storage, max_age_s=3600)
    assert counts["staging"] == 1
    assert not any(staging.glob("*/images/a.jpg")) and not any(staging.glob("*.lock"))


def test_work_folder_of_a_killed_worker_goes_once_its_job_is_final(
    tmp_path: Path, service: tuple[sessionmaker[Session], dict[str, str]]
) -> None:
    factory, env = service
    with factory.begin() as s:
        job = Job(kind=JobKind.object, task_name="object.prepare", state=JobState.queued)
        s.add(job)
        s.flush()
        job_id = job.id
    work = tmp_path / "files" / ".work" / job_id
    _kill_when(WORKER, job_id, env, work.is_dir)
    storage = LocalStorage(tmp_path / "files")
    with factory.begin() as s:
        assert s.get_one(Job, job_id).state == JobState.running
        assert retention.cleanup_files(s, storage, max_age_s=3600)["work"] == 0
    assert work.is_dir()  # a running (or requeued) job may resume from it
    # the sweeper gives up on it (its heartbeat stopped; no attempts left) ...
    later = utcnow() + timedelta(hours=1)
    with factory.begin() as s:
        assert jobs.sweep(s, Settings(max_job_attempts=1), now=later)["failed"] == 1
    # ... and the next cleanup removes its work folder
    with factory.begin() as s:
        assert retention.cleanup_files(s, storage, max_age_s=3600)["work"] == 1
    assert not work.exists()
