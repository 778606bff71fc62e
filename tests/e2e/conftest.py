"""End-to-end fixtures: real processes (uvicorn, Celery workers, a private Redis server) on
loopback, against a fresh database built by the migrations."""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import pytest

from app.client import embedded_service, free_port
from bench.console_browser import CONSOLE_DIST
from bench.loopback import redis_command
from tests.app.conftest import create_pg_database, drop_pg_database, migrate
from tests.conftest import REPO_ROOT
from tests.e2e.console_fixtures import EMBEDDED_ADMIN_KEY, ProcessedScene, process_small_scene

ADMIN_KEY = "td_e2e_admin_key_0123456789abcdef"
SECRET_KEY = "td_e2e_secret_key_0123456789abcdefghijklmnop"  # encrypts secrets at rest


def wait_until(
    check: Callable[[], bool], timeout_s: float, what: str, every_s: float = 0.1
) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if check():
            return
        time.sleep(every_s)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


@dataclass
class RedisServer:
    """A private redis-server, so tests can restart it without disturbing anything else."""

    port: int
    dir: Path
    proc: subprocess.Popen[bytes] | None = None

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    def start(self) -> None:
        binary = shutil.which("redis-server")
        if binary is None:
            pytest.fail("redis-server is not installed (the suite needs Redis: see README)")
        self.proc = subprocess.Popen(
            redis_command(binary, self.port, self.dir),
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        wait_until(self._answers, 10, "redis-server to answer")

    def _answers(self) -> bool:
        try:
            with socket.create_connection(("127.0.0.1", self.port), timeout=0.2) as s:
                s.sendall(b"PING\r\n")
                return s.recv(16).startswith(b"+PONG")
        except OSError:
            return False

    def stop(self) -> None:
        if self.proc is not None:
            self.proc.terminate()
            self.proc.wait(timeout=10)
            self.proc = None

    def restart(self) -> None:
        self.stop()
        self.start()


@pytest.fixture
def redis_server(tmp_path: Path) -> Iterator[RedisServer]:
    server = RedisServer(port=free_port(), dir=tmp_path)
    server.start()
    yield server
    server.stop()


@pytest.fixture
def pg_url() -> Iterator[str]:
    name = f"twindelta_e2e_{uuid.uuid4().hex[:8]}"
    url = create_pg_database(name)
    migrate(url)
    yield url
    drop_pg_database(name)


@dataclass
class Processes:
    """Service processes started with one environment; stopped (killed) at teardown."""

    env: dict[str, str]
    logs: Path
    procs: dict[str, subprocess.Popen[bytes]] = field(default_factory=dict)

    def start(self, name: str, argv: list[str]) -> subprocess.Popen[bytes]:
        log = (self.logs / f"{name}.log").open("ab")
        proc = subprocess.Popen(
            argv,
            env=self.env,
            cwd=REPO_ROOT,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        self.procs[name] = proc
        return proc

    def api(self, port: int, name: str = "api") -> None:
        self.start(
            name,
            [
                sys.executable,
                "-m",
                "uvicorn",
                "app.main:create_app",
                "--factory",
                "--host",
                "127.0.0.1",
                "--port",
                str(port),
                "--log-level",
                "warning",
            ],
        )

    def worker(self, name: str, queues: str, *extra: str) -> None:
        self.start(
            name,
            [
                sys.executable,
                "-m",
                "celery",
                "-A",
                "workers.celery_app",
                "worker",
                "-Q",
                queues,
                "-c",
                "1",
                "-n",
                f"{name}-{uuid.uuid4().hex[:6]}@%h",
                "--loglevel",
                "INFO",
                *extra,
            ],
        )

    def kill(self, name: str) -> None:
        """SIGKILL the whole process group: the worker and its pool children."""
        proc = self.procs.pop(name)
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)

    def stop_all(self) -> None:
        """SIGKILL every process group: at teardown nothing reads them any more, and a
        Celery warm shutdown takes seconds (``serve``'s, with its CPU worker, up to 20 s)."""
        for name in list(self.procs):
            with contextlib.suppress(ProcessLookupError):
                self.kill(name)

    def log_tail(self) -> str:
        return "\n".join(
            f"--- {p.name}\n" + p.read_text(errors="replace")[-3000:]
            for p in self.logs.glob("*.log")
        )


def service_env(data_dir: Path, **settings: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("TWINDELTA_")}
    env.update(
        TWINDELTA_DATA_DIR=str(data_dir),
        TWINDELTA_BOOTSTRAP_ADMIN_KEY=ADMIN_KEY,
        TWINDELTA_SECRET_KEY=SECRET_KEY,
        TWINDELTA_HEARTBEAT_INTERVAL_S="0.5",
        TWINDELTA_HEARTBEAT_TIMEOUT_S="4",
        TWINDELTA_SWEEP_INTERVAL_S="1",
        TWINDELTA_REQUEUE_AFTER_S="2",
        TWINDELTA_PROGRESS_INTERVAL_S="0.2",
        PYTHONUNBUFFERED="1",
    )
    env.update({f"TWINDELTA_{k.upper()}": v for k, v in settings.items()})
    return env


@pytest.fixture
def processes(tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[Callable[..., Processes]]:
    made: list[Processes] = []

    def make(**settings: str) -> Processes:
        data = tmp_path / "data"
        data.mkdir(exist_ok=True)
        procs = Processes(env=service_env(data, **settings), logs=tmp_path)
        made.append(procs)
        return procs

    yield make
    for procs in made:
        procs.stop_all()
        rep = getattr(request.node, "rep_call", None)
        if rep is not None and rep.failed:
            print(procs.log_tail())


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> Iterator[None]:
    rep = yield
    setattr(item, f"rep_{rep.when}", rep)
    return rep


FAKE_PIPELINE = "tests.e2e.fake_pipeline_plugin"  # a worker's --include: the pipeline faked


def worker_ready(log: Path) -> bool:
    """Whether a Celery worker's log says it takes tasks."""
    return log.exists() and " ready." in log.read_text(errors="replace")


def fake_pipeline_service(procs: Processes, worker: str = "cpu") -> httpx.Client:
    """Start the API and one cpu-queue worker running the fake pipeline; an admin client
    once the API answers and the worker is ready (raises TimeoutError after 120 s)."""
    port = free_port()
    procs.api(port)
    procs.worker(worker, "cpu", "--include", FAKE_PIPELINE)
    client = api_client(port)
    log = procs.logs / f"{worker}.log"
    wait_until(lambda: worker_ready(log), 120, f"worker {worker}")
    return client


def api_client(port: int) -> httpx.Client:
    client = httpx.Client(
        base_url=f"http://127.0.0.1:{port}",
        headers={"Authorization": f"Bearer {ADMIN_KEY}"},
        timeout=30,
    )
    wait_until(lambda: _up(client), 30, "the API to answer /readyz", every_s=0.2)
    return client


def _up(client: httpx.Client) -> bool:
    try:
        return client.get("/readyz").status_code == 200
    except httpx.TransportError:
        return False


def poll_job(
    client: httpx.Client,
    job_id: str,
    timeout_s: float,
    until: Callable[[dict[str, object]], bool] | None = None,
) -> dict[str, object]:
    """Poll a job until it is final (or ``until`` holds); returns the last body."""
    final = {"succeeded", "failed", "cancelled"}
    last: dict[str, object] = {}

    def done() -> bool:
        nonlocal last
        last = client.get(f"/v1/jobs/{job_id}").json()
        return until(last) if until else last["state"] in final

    wait_until(done, timeout_s, f"job {job_id} (last: {last})", every_s=0.1)
    return last


@pytest.fixture(scope="session")
def embedded_api(tmp_path_factory: pytest.TempPathFactory) -> Iterator[httpx.Client]:
    """``twindelta serve`` (SQLite, file-system broker) serving console/dist at /ui/; an
    admin client. One service for the session: the full flow and the console's tests."""
    work = tmp_path_factory.mktemp("embedded")
    with embedded_service(
        work / "data", EMBEDDED_ADMIN_KEY, work / "service.log", console_dir=str(CONSOLE_DIST)
    ) as client:
        yield client


@pytest.fixture(scope="session")
def small_scene(
    embedded_api: httpx.Client, tmp_path_factory: pytest.TempPathFactory
) -> ProcessedScene:
    """The embedded service once it has processed the 16-view 640x480 'moved' scene (two
    reconstructions and the automatic comparison, 1-3 min): see process_small_scene."""
    return process_small_scene(embedded_api, tmp_path_factory.mktemp("scene"))
