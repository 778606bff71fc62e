"""A capture station's view of twindelta over HTTP (httpx): start the embedded service, upload
captures, poll jobs with progress. Shared by the demo (``workers.demo``), the benchmarks and
the e2e tests. Imports nothing from the service (import-linter checks it): the service is a
child process, reached only over HTTP."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx

REPO_ROOT = Path(__file__).resolve().parents[1]
FINAL = {"succeeded", "failed", "cancelled"}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


@contextmanager
def embedded_service(
    data_dir: Path, admin_key: str, log_path: Path, port: int | None = None, **settings: str
) -> Iterator[httpx.Client]:
    """``twindelta serve`` in a child process (SQLite, file-system broker); yields a client
    with the admin key; stops the service on exit."""
    port = port or free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("TWINDELTA_")}
    env.update(
        TWINDELTA_DATA_DIR=str(data_dir),
        TWINDELTA_BOOTSTRAP_ADMIN_KEY=admin_key,
        PYTHONUNBUFFERED="1",
    )
    env.update({f"TWINDELTA_{k.upper()}": v for k, v in settings.items()})
    log_path.parent.mkdir(parents=True, exist_ok=True)
    with log_path.open("ab") as log:
        proc = subprocess.Popen(
            [sys.executable, "-m", "app.cli", "serve", "--port", str(port)],
            cwd=REPO_ROOT,
            env=env,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
    client = httpx.Client(
        base_url=f"http://127.0.0.1:{port}",
        timeout=120,
        headers={"Authorization": f"Bearer {admin_key}"},
    )
    try:
        deadline = time.monotonic() + 90
        while True:
            if proc.poll() is not None:
                raise RuntimeError(f"the service exited with {proc.returncode}; see {log_path}")
            try:
                if client.get("/readyz").status_code == 200:
                    break
            except httpx.TransportError:
                pass
            if time.monotonic() > deadline:
                raise RuntimeError(f"the service did not start in 90 s; see {log_path}")
            time.sleep(0.3)
        yield client
    finally:
        client.close()
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGTERM)
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)


def check(response: httpx.Response, *expected: int) -> dict[str, Any]:
    if response.status_code not in expected:
        raise RuntimeError(
            f"{response.request.method} {response.request.url.path}: "
            f"{response.status_code} {response.text[:500]}"
        )
    body: dict[str, Any] = response.json()
    return body


def capture_parts(capture_dir: Path) -> list[tuple[str, Path]]:
    """The multipart fields of a capture folder (images/, labels/, cameras.json when there):
    (field name, file) pairs in upload order."""
    parts = [
        (field, path)
        for field, sub in (("images", "images"), ("detections", "labels"))
        for path in sorted((capture_dir / sub).iterdir())
    ]
    cameras = capture_dir / "cameras.json"
    return [*parts, ("cameras", cameras)] if cameras.exists() else parts


def upload_capture(
    client: httpx.Client, environment_id: str, capture_dir: Path, idempotency_key: str | None = None
) -> dict[str, Any]:
    """POST a capture folder (:func:`capture_parts`) as multipart files, streamed."""
    handles = []
    try:
        files: list[tuple[str, tuple[str, Any]]] = []
        for field, path in capture_parts(capture_dir):
            handle = path.open("rb")
            handles.append(handle)
            files.append((field, (path.name, handle)))
        headers = {"Idempotency-Key": idempotency_key} if idempotency_key else {}
        return check(
            client.post(
                f"/v1/environments/{environment_id}/snapshots", files=files, headers=headers
            ),
            202,
        )
    finally:
        for handle in handles:
            handle.close()


def poll_job(
    client: httpx.Client, job_id: str, label: str, timeout_s: float = 1800, quiet: bool = False
) -> dict[str, Any]:
    """Poll until the job is final, drawing a one-line progress bar; returns the job."""
    started = time.monotonic()
    last_line = ""
    while True:
        job = check(client.get(f"/v1/jobs/{job_id}"), 200)
        bar = "#" * int(job["progress"] * 30)
        line = f"  {label:<28} [{bar:<30}] {job['progress'] * 100:5.1f}%  {job['state']}"
        line += f" · {job['stage']}" if job.get("stage") else ""
        if not quiet and line != last_line:
            print("\r" + line.ljust(100), end="", flush=True)
            last_line = line
        if job["state"] in FINAL:
            if not quiet:
                print(f"  ({time.monotonic() - started:.0f} s)")
            return job
        if time.monotonic() - started > timeout_s:
            raise RuntimeError(f"{label}: job {job_id} not finished after {timeout_s} s")
        time.sleep(0.5)


def read_json(path: Path) -> Any:
    return json.loads(path.read_text())
