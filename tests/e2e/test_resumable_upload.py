"""Resumable uploads for real: the API (uvicorn, embedded SQLite) and a cpu worker with the
fake pipeline (:mod:`tests.e2e.fake_pipeline_plugin`), reached through a loopback TCP proxy
that cuts every connection when the bytes sent reach 30 %, 60 % and 90 % of a 200 MB
capture; the typed client (:class:`app.client.Client`) resumes and exactly one snapshot is
made. Also the independent tus client ``tuspy`` against the same server, and the
``twindelta upload --wait`` command, whose re-run makes no second snapshot."""

from __future__ import annotations

import contextlib
import io
import os
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import numpy as np
import pytest
from PIL import Image
from tusclient.client import TusClient

from app.client import Client, pack_capture
from tests.app.conftest import migrate
from tests.conftest import REPO_ROOT
from tests.e2e.conftest import (
    ADMIN_KEY,
    FAKE_PIPELINE,
    Processes,
    api_client,
    free_port,
    poll_job,
    service_env,
    wait_until,
    worker_ready,
)

pytestmark = [pytest.mark.slow, pytest.mark.e2e]

CLASSES = ["drill", "bowl", "mug"]
UPLOAD_MB = 200


@dataclass
class Service:
    port: int
    http: httpx.Client
    data_dir: Path

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def environment(self, name: str) -> str:
        r = self.http.post("/v1/environments", json={"name": name, "classes": CLASSES})
        assert r.status_code == 201, r.text
        env_id: str = r.json()["id"]
        return env_id

    def snapshots(self, env_id: str) -> list[dict[str, object]]:
        r = self.http.get(f"/v1/environments/{env_id}/snapshots")
        assert r.status_code == 200, r.text
        found: list[dict[str, object]] = r.json()
        return found


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Service]:
    """One API and one cpu worker (fake pipeline) for the module."""
    root = tmp_path_factory.mktemp("resumable")
    data = root / "data"
    data.mkdir()
    migrate(f"sqlite:///{data / 'twindelta.db'}")
    procs = Processes(env=service_env(data), logs=root)
    port = free_port()
    procs.api(port)
    procs.worker("cpu", "cpu", "--include", FAKE_PIPELINE)
    try:
        http = api_client(port)
        log = root / "cpu.log"
        wait_until(lambda: worker_ready(log), 120, "the cpu worker")
        yield Service(port=port, http=http, data_dir=data)
    except BaseException:
        print(procs.log_tail())
        raise
    finally:
        procs.stop_all()


def noise_jpeg(seed: int, width: int, height: int) -> bytes:
    pixels = np.random.default_rng(seed).integers(0, 255, (height, width, 3), dtype=np.uint8)
    out = io.BytesIO()
    Image.fromarray(pixels).save(out, "JPEG", quality=95)
    return out.getvalue()


def write_capture(folder: Path, scene: dict[str, float], big_mb: int = 0) -> Path:
    """Three small photos with YOLO labels (one box per class in ``scene``, centre x =
    the value), plus large incompressible photos (20 MP noise JPEGs, within the image
    limits) until the capture holds ``big_mb`` MB."""
    (folder / "images").mkdir(parents=True)
    (folder / "labels").mkdir()
    labels = "".join(f"{CLASSES.index(n)} {x} 0.5 0.1 0.1\n" for n, x in scene.items())
    for i in range(3):
        (folder / "images" / f"v{i}.jpg").write_bytes(noise_jpeg(i, 64, 48))
        (folder / "labels" / f"v{i}.txt").write_text(labels)
    bodies = [noise_jpeg(100 + i, 5000, 4000) for i in range(2)] if big_mb else []
    total, n = 0, 0
    while total < big_mb * 1e6:
        body = bodies[n % 2]
        (folder / "images" / f"big{n:02d}.jpg").write_bytes(body)
        total, n = total + len(body), n + 1
    return folder


class CuttingProxy:
    """A loopback TCP proxy to ``target_port`` that counts the bytes clients send and, each
    time that count reaches the next of ``cuts``, closes every open connection at once."""

    def __init__(self, target_port: int, cuts: list[int]) -> None:
        self.target_port, self.cuts = target_port, sorted(cuts)
        self.sent = 0
        self.n_cuts = 0
        self.lock = threading.Lock()
        self.open: set[socket.socket] = set()
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self.listener.accept()
            except OSError:
                return
            upstream = socket.create_connection(("127.0.0.1", self.target_port))
            with self.lock:
                self.open |= {client, upstream}
            threading.Thread(target=self._pump, args=(client, upstream, True), daemon=True).start()
            threading.Thread(target=self._pump, args=(upstream, client, False), daemon=True).start()

    def _pump(self, src: socket.socket, dst: socket.socket, counted: bool) -> None:
        try:
            while data := src.recv(256 * 1024):
                if counted:
                    with self.lock:
                        if self.cuts and self.sent + len(data) >= self.cuts[0]:
                            keep = self.cuts.pop(0) - self.sent
                            self.sent += len(data)
                            dst.sendall(data[:keep])
                            self.n_cuts += 1
                            self._cut_all()
                            return
                        self.sent += len(data)
                dst.sendall(data)
        except OSError:
            pass
        finally:
            for sock in (src, dst):
                self._close(sock)

    def _cut_all(self) -> None:
        for sock in list(self.open):
            self._close(sock)

    def _close(self, sock: socket.socket) -> None:
        with contextlib.suppress(OSError):
            sock.shutdown(socket.SHUT_RDWR)
        sock.close()
        self.open.discard(sock)

    def close(self) -> None:
        self.listener.close()
        with self.lock:
            self._cut_all()


def test_a_200_mb_upload_cut_at_30_60_90_percent_resumes_into_one_snapshot(
    service: Service, tmp_path: Path
) -> None:
    env_id = service.environment("cell-cut")
    capture = write_capture(tmp_path / "capture", {"drill": 0.2, "bowl": 0.5}, UPLOAD_MB)
    packed = pack_capture(capture, tmp_path / "capture.tar")
    assert packed.size > UPLOAD_MB * 1e6
    proxy = CuttingProxy(service.port, [int(packed.size * f) for f in (0.3, 0.6, 0.9)])
    try:
        with Client(f"http://127.0.0.1:{proxy.port}", ADMIN_KEY, backoff_s=0.2) as client:
            result = client.upload(
                env_id, packed.path, sha256=packed.sha256, idempotency_key=packed.idempotency_key
            )
    finally:
        proxy.close()
    assert proxy.n_cuts == 3
    assert result.resumes >= 3
    assert proxy.sent <= 1.1 * packed.size, (proxy.sent, packed.size)
    print(
        f"{proxy.sent} bytes through the proxy for a {packed.size}-byte upload "
        f"({proxy.sent / packed.size:.3f}x), {result.resumes} resumes"
    )
    snaps = service.snapshots(env_id)
    assert [s["id"] for s in snaps] == [result.snapshot]
    assert snaps[0]["upload_bytes"] == sum(
        p.stat().st_size for p in capture.rglob("*") if p.is_file()
    )
    job = poll_job(service.http, result.job, 120)
    assert job["state"] == "succeeded", job
    uploads_dir = service.data_dir / "files" / "uploads"
    assert not (uploads_dir / result.upload_url.rsplit("/", 1)[1]).exists()
    # The same archive again, straight: the completed upload is found, nothing is resent.
    with Client(service.url, ADMIN_KEY) as client:
        again = client.upload(
            env_id, packed.path, sha256=packed.sha256, idempotency_key=packed.idempotency_key
        )
    assert (again.snapshot, again.bytes_sent) == (result.snapshot, 0)
    assert len(service.snapshots(env_id)) == 1


def test_tuspy_uploads_and_resumes_against_the_server(service: Service, tmp_path: Path) -> None:
    env_id = service.environment("cell-tuspy")
    capture = write_capture(tmp_path / "capture", {"drill": 0.3})
    packed = pack_capture(capture, tmp_path / "capture.tar")
    tus = TusClient(f"{service.url}/v1/uploads", headers={"Authorization": f"Bearer {ADMIN_KEY}"})
    first = tus.uploader(
        str(packed.path),
        chunk_size=4096,
        metadata={"environment_id": env_id, "filename": "capture.tar"},
        upload_checksum=True,  # sha1 Upload-Checksum on every PATCH
    )
    first.upload(stop_at=packed.size // 2)
    assert first.url is not None and packed.size // 2 <= first.offset < packed.size
    # A second client knows only the URL: it asks the offset (HEAD) and goes on from there.
    second = tus.uploader(str(packed.path), url=first.url, chunk_size=64 * 1024)
    assert second.offset == first.offset
    second.upload()
    assert second.request is not None
    headers = {k.lower(): v for k, v in second.request.response_headers.items()}
    snapshot_id, job_id = headers["twindelta-snapshot"], headers["twindelta-job"]
    assert [s["id"] for s in service.snapshots(env_id)] == [snapshot_id]
    assert poll_job(service.http, job_id, 60)["state"] == "succeeded"
    r = service.http.head(first.url, headers={"Tus-Resumable": "1.0.0"})
    assert r.headers["Upload-Offset"] == str(packed.size)


def run_cli(*args: str) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("TWINDELTA_")}
    env["TWINDELTA_API_KEY"] = ADMIN_KEY
    return subprocess.run(
        [sys.executable, "-m", "app.cli", *args],
        cwd=REPO_ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_cli_upload_wait_prints_the_changes_and_a_rerun_makes_no_second_snapshot(
    service: Service, tmp_path: Path
) -> None:
    env_id = service.environment("cell-cli")
    before = write_capture(tmp_path / "before", {"drill": 0.2, "bowl": 0.5})
    after = write_capture(tmp_path / "after", {"drill": 0.4, "mug": 0.7})
    url = ("--url", service.url)
    done = run_cli("upload", str(before), "--env", "cell-cli", "--wait", *url)
    assert done.returncode == 0, done.stderr
    assert "no comparison: the first snapshot" in done.stdout
    assert "upload   [" in done.stderr and "job      [" in done.stderr
    done = run_cli("upload", str(after), "--env", "cell-cli", "--wait", *url)
    assert done.returncode == 0, done.stderr
    rows = {line.split()[0]: line.split()[1] for line in done.stdout.splitlines()[3:]}
    assert rows == {"moved": "drill", "removed": "bowl", "added": "mug"}, done.stdout
    first_run = done.stdout
    assert len(service.snapshots(env_id)) == 2
    rerun = run_cli("upload", str(after), "--env", env_id, "--wait", *url)
    assert rerun.returncode == 0, rerun.stderr
    assert len(service.snapshots(env_id)) == 2
    assert rerun.stdout == first_run  # the same snapshot, job and changes
    state = run_cli("state", "--env", "cell-cli", "--json", *url)
    assert state.returncode == 0, state.stderr
    assert "mug" in state.stdout and "bowl" not in state.stdout
    changes = run_cli("changes", "--env", "cell-cli", *url)
    assert changes.returncode == 0 and "moved" in changes.stdout
    (tmp_path / "empty").mkdir()
    bad = run_cli("upload", str(tmp_path / "empty"), "--env", "cell-cli", *url)
    assert bad.returncode == 1 and "no images" in bad.stderr
    missing = run_cli("upload", str(tmp_path / "missing"), "--env", "cell-cli", *url)
    assert missing.returncode == 1 and "missing: no such folder" in missing.stderr
    unknown = run_cli("state", "--env", "no-such-cell", *url)
    assert unknown.returncode == 1 and "no-such-cell" in unknown.stderr
