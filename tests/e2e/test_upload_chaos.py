"""Uploads under faults, with real processes: the API (uvicorn, embedded SQLite) killed in
the middle of an upload and restarted, and the storage's disk filling up during one (a
20 MiB tmpfs). Each ends cleanly: a clear JSON answer or a retry that succeeds, no partial
snapshot rows, no staged files left behind, and the earlier snapshot untouched."""

from __future__ import annotations

import hashlib
import io
import os
import subprocess
import threading
import time
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
from PIL import Image

from tests.app.conftest import migrate
from tests.e2e.conftest import Processes, api_client, free_port

pytestmark = [pytest.mark.slow, pytest.mark.e2e]

CLASSES = ["power_drill", "bowl"]


def jpeg(seed: int, size: tuple[int, int] = (64, 48)) -> bytes:
    rng = np.random.default_rng(seed)
    out = io.BytesIO()
    Image.fromarray(rng.integers(0, 255, (size[1], size[0], 3), dtype=np.uint8)).save(
        out, "JPEG", quality=95
    )
    return out.getvalue()


def parts(images: dict[str, bytes]) -> list[tuple[str, tuple[str, bytes]]]:
    files = [("images", (name, body)) for name, body in images.items()]
    stem = Path(next(iter(images))).stem
    files.append(("detections", (f"{stem}.txt", b"0 0.5 0.5 0.2 0.3\n")))
    return files


def small_capture(seed: int = 0) -> dict[str, bytes]:
    return {f"a{i}.jpg": jpeg(seed + i) for i in range(3)}


def stored(root: Path, under: str = "snapshots") -> dict[str, str]:
    base = root / under
    if not base.is_dir():
        return {}
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(base.rglob("*"))
        if p.is_file()
    }


def staging_left(root: Path) -> list[str]:
    tmp = root / ".tmp"
    return sorted(p.name for p in tmp.iterdir()) if tmp.is_dir() else []


def n_snapshots(client: httpx.Client, env_id: str) -> int:
    r = client.get(f"/v1/environments/{env_id}/snapshots")
    assert r.status_code == 200, r.text
    body = r.json()
    items = body["items"] if isinstance(body, dict) else body
    return len(items)


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    """A 20 MiB tmpfs for the storage folder (the suite runs as root in CI and here)."""
    mount = tmp_path / "small-disk"
    mount.mkdir()
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=20m", "tmpfs", str(mount)],
        capture_output=True,
        text=True,
        check=False,
    )
    if done.returncode != 0:
        pytest.fail(f"cannot mount a tmpfs (the disk-full test needs root): {done.stderr}")
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=False)


def start_api(procs: Processes) -> tuple[int, httpx.Client]:
    """uvicorn on the embedded SQLite file in the data folder (built by the migrations)."""
    database = Path(procs.env["TWINDELTA_DATA_DIR"]) / "twindelta.db"
    if not database.exists():
        migrate(f"sqlite:///{database}")
    port = free_port()
    procs.api(port)
    return port, api_client(port)


def test_disk_full_during_an_upload_is_a_clean_507(
    processes: Callable[..., Processes], small_disk: Path
) -> None:
    procs = processes(storage_dir=str(small_disk))
    _, client = start_api(procs)
    env = client.post("/v1/environments", json={"name": "cell", "classes": CLASSES})
    assert env.status_code == 201, env.text
    env_id = env.json()["id"]
    first = client.post(f"/v1/environments/{env_id}/snapshots", files=parts(small_capture()))
    assert first.status_code == 202, first.text
    before = stored(small_disk)
    assert before

    # 25 MB of photos (incompressible) does not fit on a 20 MiB disk: loose, then zipped
    big = dict(small_capture(10))
    rng = np.random.default_rng(7)
    big["big.jpg"] = jpeg(99) + rng.bytes(25 * 1024**2)
    zipped = io.BytesIO()
    with zipfile.ZipFile(zipped, "w", zipfile.ZIP_STORED) as zf:
        for name, body in big.items():
            zf.writestr(f"cap/{name}", body)
        zf.writestr("cap/a0.txt", b"0 0.5 0.5 0.2 0.3\n")
    for files in (parts(big), [("archive", ("c.zip", zipped.getvalue()))]):
        r = client.post(f"/v1/environments/{env_id}/snapshots", files=files, timeout=120)
        assert r.status_code == 507, r.text
        assert r.json()["error"] == "InsufficientStorage", r.text
        assert str(small_disk) not in r.json()["detail"]
        assert staging_left(small_disk) == []
        assert stored(small_disk) == before  # the earlier snapshot untouched
        assert n_snapshots(client, env_id) == 1  # no partial row

    # the space came back: the next upload goes through
    again = client.post(f"/v1/environments/{env_id}/snapshots", files=parts(small_capture(20)))
    assert again.status_code == 202, again.text
    assert n_snapshots(client, env_id) == 2
    assert staging_left(small_disk) == []


def slow_capture(n: int = 60) -> dict[str, bytes]:
    """Enough large photos that staging and checking them takes a visible while."""
    return {f"a{i:03d}.jpg": jpeg(i, (1600, 1200)) for i in range(n)}


def test_api_killed_mid_upload_then_restarted_retry_succeeds(
    processes: Callable[..., Processes], tmp_path: Path
) -> None:
    procs = processes()
    storage = tmp_path / "data" / "files"
    _, client = start_api(procs)
    env = client.post("/v1/environments", json={"name": "cell", "classes": CLASSES})
    assert env.status_code == 201, env.text
    env_id = env.json()["id"]
    first = client.post(f"/v1/environments/{env_id}/snapshots", files=parts(small_capture()))
    assert first.status_code == 202, first.text
    before = stored(storage)

    capture = parts(slow_capture())
    headers = {"Idempotency-Key": "capture-0042"}
    outcome: list[object] = []

    def send() -> None:
        try:
            outcome.append(
                client.post(
                    f"/v1/environments/{env_id}/snapshots",
                    files=capture,
                    headers=headers,
                    timeout=120,
                )
            )
        except httpx.TransportError as exc:
            outcome.append(exc)

    uploader = threading.Thread(target=send)
    uploader.start()
    # Kill the API (SIGKILL: no clean-up of any kind) while it stages the upload.
    staged = False
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and uploader.is_alive():
        if any(not name.endswith(".lock") for name in staging_left(storage)):
            staged = True
            break
        time.sleep(0.002)
    procs.kill("api")
    uploader.join(timeout=60)
    assert staged, f"the upload finished before it could be interrupted: {outcome}"
    assert outcome and isinstance(outcome[0], httpx.TransportError), outcome
    assert staging_left(storage), "the killed upload left its staging folder"

    _, client = start_api(procs)
    assert staging_left(storage) == []  # the restarted API swept the dead upload's folder
    assert n_snapshots(client, env_id) == 1  # nothing half-made became a snapshot
    retry = client.post(
        f"/v1/environments/{env_id}/snapshots", files=capture, headers=headers, timeout=120
    )
    assert retry.status_code == 202, retry.text
    replay = client.post(
        f"/v1/environments/{env_id}/snapshots", files=capture, headers=headers, timeout=120
    )
    assert replay.status_code == 202 and replay.headers.get("idempotent-replayed") == "true"
    assert replay.json()["snapshot"]["id"] == retry.json()["snapshot"]["id"]
    assert n_snapshots(client, env_id) == 2
    snap = client.get(f"/v1/snapshots/{retry.json()['snapshot']['id']}").json()
    assert snap["n_images"] == 60
    # the dead process's staging folder was swept; the earlier snapshot is untouched
    assert staging_left(storage) == []
    after = stored(storage)
    assert {k: v for k, v in after.items() if k in before} == before
    new_files = set(after) - set(before)
    assert new_files and all(
        k.startswith(f"snapshots/{retry.json()['snapshot']['id']}/") for k in new_files
    )
    assert os.listdir(storage / "snapshots") and len(os.listdir(storage / "snapshots")) == 2
