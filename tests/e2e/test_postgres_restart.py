"""PostgreSQL restarted in the middle of a job: the job finishes, exactly once.

The test starts its own PostgreSQL server (initdb + pg_ctl from /usr/lib/postgresql/*/bin,
on a free port, in a temporary folder owned by the ``postgres`` user when the suite runs as
root), so restarting it disturbs no other test. The job is the real object job
(``workers.objects``: its own database read, ``prepare_model``, its own persist) run by the
production runner, with one extra stage in front that reports progress as often as a
reconstruction does, so the restart lands on progress writes: once in this process, once in
the production processes (API, Celery worker and beat on a private Redis).
"""

from __future__ import annotations

import logging
import os
import pwd
import shutil
import subprocess
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import open3d as o3d
import pytest
from sqlalchemy import create_engine, select, text
from sqlalchemy.orm import sessionmaker

from app.client import free_port
from app.core import db, jobs, objects, queue
from app.core.db import transaction
from app.core.enums import JobState, ObjectState
from app.core.models import Event, Job
from app.core.settings import get_settings
from app.core.storage import LocalStorage
from tests.app.conftest import migrate
from tests.e2e.conftest import Processes, RedisServer, api_client, wait_until

pytestmark = [pytest.mark.slow, pytest.mark.e2e, pytest.mark.postgres, pytest.mark.redis]


def pg_bin() -> Path:
    found = sorted(Path("/usr/lib/postgresql").glob("*/bin/pg_ctl"))
    if not found:
        pytest.fail("PostgreSQL server binaries not found under /usr/lib/postgresql/*/bin")
    return found[-1].parent


@dataclass
class PostgresServer:
    """A private PostgreSQL server that a test may stop and start."""

    port: int
    dir: Path

    @property
    def url(self) -> str:
        return f"postgresql+psycopg://postgres@127.0.0.1:{self.port}/twindelta"

    def _run(self, *argv: str) -> None:
        # initdb refuses to run as root: run the server's tools as its owner
        prefix = ["runuser", "-u", "postgres", "--"] if os.geteuid() == 0 else []
        subprocess.run([*prefix, *argv], check=True, capture_output=True, timeout=60)

    def init(self) -> None:
        self._run(
            str(pg_bin() / "initdb"), "-D", str(self.dir / "data"), "-A", "trust", "-U", "postgres"
        )

    def start(self) -> None:
        options = f"-p {self.port} -k {self.dir} -c listen_addresses=127.0.0.1 -c fsync=off"
        self._run(
            str(pg_bin() / "pg_ctl"),
            "-D",
            str(self.dir / "data"),
            "-l",
            str(self.dir / "server.log"),
            "-o",
            options,
            "-w",
            "-t",
            "30",
            "start",
        )

    def stop(self) -> None:
        self._run(
            str(pg_bin() / "pg_ctl"), "-D", str(self.dir / "data"), "-m", "fast", "-w", "stop"
        )


@pytest.fixture
def private_postgres() -> Iterator[PostgresServer]:
    folder = Path(tempfile.mkdtemp(prefix="twindelta-pg-"))
    if os.geteuid() == 0:
        owner = pwd.getpwnam("postgres")
        os.chown(folder, owner.pw_uid, owner.pw_gid)
    server = PostgresServer(port=free_port(), dir=folder)
    server.init()
    server.start()
    admin = create_engine(
        f"postgresql+psycopg://postgres@127.0.0.1:{server.port}/postgres",
        isolation_level="AUTOCOMMIT",
    )
    with admin.connect() as conn:
        conn.execute(text("CREATE DATABASE twindelta"))
    admin.dispose()
    migrate(server.url)
    try:
        yield server
    finally:
        try:
            server.stop()
        finally:
            shutil.rmtree(folder, ignore_errors=True)


@pytest.fixture
def worker_settings(
    private_postgres: PostgresServer, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> Iterator[list[tuple[str, dict[str, Any]]]]:
    """This process configured as a worker on the private server; sent tasks recorded."""
    monkeypatch.setenv("TWINDELTA_DATA_DIR", str(tmp_path / "data"))
    monkeypatch.setenv("TWINDELTA_DATABASE_URL", private_postgres.url)
    monkeypatch.setenv("TWINDELTA_PROGRESS_INTERVAL_S", "0.02")
    monkeypatch.setenv("TWINDELTA_HEARTBEAT_INTERVAL_S", "0.5")
    monkeypatch.setenv("TWINDELTA_DB_RETRY_S", "60")
    monkeypatch.delenv("TWINDELTA_BROKER_URL", raising=False)
    get_settings.cache_clear()
    sent: list[tuple[str, dict[str, Any]]] = []
    monkeypatch.setattr(queue, "send_now", lambda name, **kw: sent.append((name, kw)))
    engine = db.make_engine(private_postgres.url)
    db.use_session_factory(sessionmaker(bind=engine, expire_on_commit=False))
    yield sent
    db.use_session_factory(None)
    engine.dispose()
    get_settings.cache_clear()


def test_postgres_restart_mid_job_finishes_exactly_once(
    private_postgres: PostgresServer,
    worker_settings: list[tuple[str, dict[str, Any]]],
    tmp_path: Path,
    caplog: pytest.LogCaptureFixture,
) -> None:
    from workers import objects as object_job
    from workers.runner import JobContext, run_job

    caplog.set_level(logging.WARNING)
    mesh = tmp_path / "torus.ply"
    o3d.io.write_triangle_mesh(str(mesh), o3d.geometry.TriangleMesh.create_torus(0.2, 0.05))
    storage = LocalStorage(get_settings().resolved_storage_dir)
    with transaction() as s, mesh.open("rb") as fh:
        obj, job = objects.create(
            s,
            storage,
            objects.ModelUpload(
                name="torus", filename="torus.ply", source=fh, units="m", symmetry=None
            ),
            max_bytes=10**8,
        )
        object_id, job_id = obj.id, job.id
    worker_settings.clear()

    restarted = threading.Event()
    reports_after_restart = 0
    persisted: list[str] = []

    def long_stage_then_prepare(ctx: JobContext) -> Any:
        """Progress every few milliseconds until the server came back (and a little after),
        then the real object computation, which reads the database again."""
        nonlocal reports_after_restart
        deadline = time.monotonic() + 60
        i = 0
        while reports_after_restart < 50 and time.monotonic() < deadline:
            ctx.progress("warmup", (i % 100) / 100)
            if restarted.is_set():
                reports_after_restart += 1
            i += 1
            time.sleep(0.005)
        return object_job._compute(ctx)

    def persist(session: Any, ctx: JobContext, model: Any) -> None:
        persisted.append(ctx.job.id)
        object_job._persist(session, ctx, model)

    outcome: list[str] = []
    runner = threading.Thread(
        target=lambda: outcome.append(run_job(job_id, long_stage_then_prepare, persist))
    )
    runner.start()

    def warming_up() -> bool:
        with transaction() as s:
            return jobs.get(s, job_id).stage == "warmup"

    wait_until(warming_up, 30, "the job to report its first stage")
    private_postgres.stop()  # terminates every connection, in-flight progress writes too
    time.sleep(1.0)  # progress reports keep coming while the server is down
    private_postgres.start()
    restarted.set()
    runner.join(timeout=120)
    assert not runner.is_alive(), "the job did not finish within 120 s of the restart"

    assert outcome == ["succeeded"]
    skipped = [r for r in caplog.records if "not written" in r.getMessage()]
    assert skipped, "no progress write met the restart; the test did not test anything"
    assert persisted == [job_id]  # the result was written once
    with transaction() as s:
        done = jobs.get(s, job_id)
        assert done.state == JobState.succeeded and done.attempts == 1
        assert done.error_code is None and done.progress == 1.0
        prepared = objects.get(s, object_id)
        assert prepared.state == ObjectState.ready
        assert prepared.diameter_m == pytest.approx(0.5, abs=0.01)
        assert s.scalars(select(Job.id).where(Job.object_id == object_id)).all() == [job_id]
        assert s.scalars(select(Event.type)).all() == []  # no job.failed
    assert worker_settings == []  # never requeued: nothing sent again


def test_postgres_restart_mid_job_in_the_service_processes(
    private_postgres: PostgresServer,
    redis_server: RedisServer,
    processes: Callable[..., Processes],
    tmp_path: Path,
) -> None:
    """The same fault with real processes: the API, a Celery worker (its object jobs slowed
    by :mod:`tests.e2e.slow_jobs`) and beat with the sweeper, all on the private server."""
    procs = processes(
        database_url=private_postgres.url, broker_url=redis_server.url, test_slow_stage_s="8"
    )
    port = free_port()
    procs.api(port)
    procs.worker("cpu", "cpu", "--include", "tests.e2e.slow_jobs")
    procs.worker("beat", "maintenance", "-B", "-s", str(tmp_path / "beat-schedule"))
    client = api_client(port)
    mesh = tmp_path / "torus.ply"
    o3d.io.write_triangle_mesh(str(mesh), o3d.geometry.TriangleMesh.create_torus(0.2, 0.05))
    r = client.post(
        "/v1/objects", files={"file": ("torus.ply", mesh.read_bytes())}, data={"name": "torus"}
    )
    assert r.status_code == 202, r.text
    object_id, job_id = r.json()["id"], r.json()["job"]["id"]

    last: dict[str, Any] = {}

    def job_is(check: Callable[[dict[str, Any]], bool]) -> Callable[[], bool]:
        def poll() -> bool:
            nonlocal last
            try:
                answer = client.get(f"/v1/jobs/{job_id}")
            except httpx.TransportError:
                return False
            if answer.status_code != 200:  # the API's database is restarting too
                return False
            last = answer.json()
            return check(last)

        return poll

    wait_until(job_is(lambda j: j["stage"] == "warmup"), 60, "the job's first stage")
    private_postgres.stop()
    time.sleep(1.0)
    private_postgres.start()
    wait_until(job_is(lambda j: j["state"] == "running"), 30, "the API to answer again")
    wait_until(
        job_is(lambda j: j["state"] in {"succeeded", "failed", "cancelled"}),
        90,
        f"job {job_id} to finish",
    )
    assert last["state"] == "succeeded", last
    assert last["attempts"] == 1 and last["error"] is None
    prepared = client.get(f"/v1/objects/{object_id}").json()
    assert prepared["state"] == "ready"
    assert prepared["diameter_m"] == pytest.approx(0.5, abs=0.01)
    worker_log = (tmp_path / "cpu.log").read_text(errors="replace")
    assert "not written" in worker_log, "no progress write met the restart"
    engine = create_engine(private_postgres.url)
    try:
        with engine.connect() as conn:
            assert conn.execute(text("SELECT count(*) FROM jobs")).scalar() == 1
            assert conn.execute(text("SELECT count(*) FROM events")).scalar() == 0
    finally:
        engine.dispose()
