"""Upload benchmark: a ~1 GB snapshot archive through the real API process, as one
multipart request and as a resumable (tus) upload.

``python bench/upload_bench.py [--size-mb 1024] [--chunk-mb 64] [--out bench/results/upload.json]``

Builds a stored (uncompressed) zip of random-noise JPEGs (incompressible, so the bytes on
the wire are the bytes stored; a few distinct images repeated under different names) with
one YOLO label file per image, starts the API as production does
(``uvicorn app.main:create_app --factory``, embedded SQLite, a temporary data folder,
a bootstrap admin key) on a free port, creates an environment, streams the archive from
disk with httpx, and records wall time, throughput and the API process's peak resident
memory (``VmHWM`` from ``/proc/<pid>/status``) against the 300 MB target. Then the same
with a fresh API process for :meth:`app.client.Client.upload` (tus PATCHes of
``--chunk-mb``), and the ratio of the two throughputs (target: within 20 %).
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import os
import platform
import secrets
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from PIL import Image

from app.client import Client, free_port

REPO_ROOT = Path(__file__).resolve().parents[1]
TARGET_PEAK_RSS_MB = 300.0
CLASSES = ["power_drill", "bowl"]


def noise_jpeg(seed: int, width: int = 1600, height: int = 1200) -> bytes:
    """A random-noise JPEG: about 1.5 bytes per pixel at quality 90, incompressible."""
    rng = np.random.default_rng(seed)
    pixels = rng.integers(0, 255, (height, width, 3), dtype=np.uint8)
    out = io.BytesIO()
    Image.fromarray(pixels).save(out, "JPEG", quality=90)
    return out.getvalue()


def build_archive(path: Path, size_bytes: int, distinct: int = 8) -> tuple[int, int]:
    """Write a stored zip of ~``size_bytes`` to ``path``; returns (bytes, images)."""
    jpegs = [noise_jpeg(seed) for seed in range(distinct)]
    rng = np.random.default_rng(0)
    n = 0
    written = 0
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as zf:
        while written < size_bytes:
            body = jpegs[n % distinct]
            zf.writestr(f"capture/images/img_{n:05d}.jpg", body)
            cx, cy = rng.uniform(0.2, 0.8, 2)
            zf.writestr(
                f"capture/labels/img_{n:05d}.txt",
                f"{n % len(CLASSES)} {cx:.4f} {cy:.4f} 0.1000 0.1500 0.87\n",
            )
            written += len(body)
            n += 1
        zf.writestr("capture/classes.txt", "\n".join(CLASSES) + "\n")
    return path.stat().st_size, n


def proc_status_kb(pid: int, field: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(f"{field}:"):
            return int(line.split()[1])
    raise KeyError(field)


class RssSampler(threading.Thread):
    """Samples VmRSS of ``pid`` every 50 ms (VmHWM gives the true peak at the end)."""

    def __init__(self, pid: int) -> None:
        super().__init__(daemon=True)
        self.pid, self.samples, self.stop = pid, [], threading.Event()
        self.samples: list[tuple[float, int]]

    def run(self) -> None:
        start = time.perf_counter()
        while not self.stop.is_set():
            try:
                self.samples.append(
                    (time.perf_counter() - start, proc_status_kb(self.pid, "VmRSS"))
                )
            except (OSError, KeyError):
                return
            time.sleep(0.05)


@dataclass
class Api:
    """A uvicorn process as production starts it, on a fresh data folder."""

    server: subprocess.Popen[bytes]
    base: str
    headers: dict[str, str]
    key: str


def start_api(workdir: Path, name: str) -> Api:
    data_dir = workdir / f"data-{name}"
    admin_key = "td_bench_" + secrets.token_hex(16)
    env = {
        **{k: v for k, v in os.environ.items() if not k.startswith("TWINDELTA_")},
        "TWINDELTA_DATA_DIR": str(data_dir),
        "TWINDELTA_BOOTSTRAP_ADMIN_KEY": admin_key,
        "TWINDELTA_MAX_UPLOAD_FILES": "100000",
        "TWINDELTA_MAX_UPLOAD_BYTES": str(16 * 1024**3),
        "TWINDELTA_MAX_FILE_BYTES": str(1024**3),
        "TMPDIR": str(workdir),  # the multipart parser's spooled files
    }
    subprocess.run([sys.executable, "-m", "app.cli", "migrate"], cwd=REPO_ROOT, env=env, check=True)
    port = free_port()
    server = subprocess.Popen(
        [sys.executable, "-m", "uvicorn", "app.main:create_app", "--factory",
         "--host", "127.0.0.1", "--port", str(port), "--log-level", "warning"],
        cwd=REPO_ROOT, env=env,
    )  # fmt: skip
    base = f"http://127.0.0.1:{port}"
    with httpx.Client(base_url=base) as client:
        for _ in range(600):
            try:
                if client.get("/healthz").status_code == 200:
                    break
            except httpx.TransportError:
                pass
            time.sleep(0.1)
    return Api(server, base, {"Authorization": f"Bearer {admin_key}"}, admin_key)


def single_upload(api: Api, env_id: str, archive: Path) -> tuple[int, dict[str, Any]]:
    """POST the archive as one multipart request; (status, snapshot)."""
    with httpx.Client(base_url=api.base, timeout=None) as client, archive.open("rb") as fh:
        r = client.post(  # httpx streams file objects in chunks
            f"/v1/environments/{env_id}/snapshots",
            files={"archive": (archive.name, fh, "application/zip")},
            headers=api.headers,
        )
    if r.status_code != 202:
        raise SystemExit(f"upload failed: {r.status_code} {r.text[:500]}")
    snapshot: dict[str, Any] = r.json()["snapshot"]
    return r.status_code, snapshot


def resumable_upload(
    api: Api, env_id: str, archive: Path, sha256: str, chunk_mb: int
) -> tuple[int, dict[str, Any]]:
    """The typed client's tus upload in PATCHes of ``chunk_mb``; (204, snapshot)."""
    with Client(api.base, api.key, timeout_s=600) as client:
        result = client.upload(env_id, archive, sha256=sha256, chunk_bytes=chunk_mb * 1024**2)
        return 204, client.snapshot(result.snapshot)


def measure(
    workdir: Path, mode: str, archive: Path, send: Callable[[Api, str, Path], tuple[int, Any]]
) -> dict[str, Any]:
    """One upload through a fresh API process: wall time and the process's peak RSS."""
    api = start_api(workdir, mode)
    try:
        with httpx.Client(base_url=api.base) as client:
            r = client.post(
                "/v1/environments", json={"name": "bench", "classes": CLASSES}, headers=api.headers
            )
            r.raise_for_status()
            env_id = r.json()["id"]
        idle_rss_kb = proc_status_kb(api.server.pid, "VmRSS")
        idle_hwm_kb = proc_status_kb(api.server.pid, "VmHWM")
        sampler = RssSampler(api.server.pid)
        sampler.start()
        t0 = time.perf_counter()
        status, snap = send(api, env_id, archive)
        seconds = time.perf_counter() - t0
        sampler.stop.set()
        sampler.join()
        peak_kb = proc_status_kb(api.server.pid, "VmHWM")
    finally:
        api.server.terminate()
        api.server.wait(30)
    shutil.rmtree(workdir / f"data-{mode}", ignore_errors=True)
    archive_bytes = archive.stat().st_size
    return {
        "status": status,
        "n_detections": snap["n_detections"],
        "seconds": round(seconds, 2),
        "mb_per_s": round(archive_bytes / 1e6 / seconds, 1),
        "peak_rss_mb": round(peak_kb / 1024, 1),
        "idle_rss_mb": round(idle_rss_kb / 1024, 1),
        "idle_hwm_mb": round(idle_hwm_kb / 1024, 1),
        "max_sampled_rss_mb": round(max((kb for _, kb in sampler.samples), default=0) / 1024, 1),
        "within_target": peak_kb / 1024 <= TARGET_PEAK_RSS_MB,
    }


def run(size_mb: int, out: Path, workdir: Path, chunk_mb: int = 64) -> dict[str, Any]:
    archive = workdir / "capture.zip"
    t0 = time.perf_counter()
    archive_bytes, n_images = build_archive(archive, size_mb * 1024**2)
    build_s = time.perf_counter() - t0
    digest = hashlib.sha256()
    with archive.open("rb") as fh:
        while chunk := fh.read(4 * 1024**2):
            digest.update(chunk)
    print(f"archive: {archive_bytes / 1e6:.0f} MB, {n_images} images ({build_s:.1f} s)")
    single = measure(workdir, "single", archive, single_upload)
    print(f"single request: {single['seconds']} s, peak RSS {single['peak_rss_mb']} MB")
    resumable = measure(
        workdir,
        "resumable",
        archive,
        lambda api, env_id, path: resumable_upload(api, env_id, path, digest.hexdigest(), chunk_mb),
    )
    print(f"resumable: {resumable['seconds']} s, peak RSS {resumable['peak_rss_mb']} MB")
    ratio = resumable["mb_per_s"] / single["mb_per_s"]
    result: dict[str, Any] = {
        "benchmark": "snapshot upload through the API process: one multipart request, and "
        "the resumable (tus) upload of the same archive",
        "archive_bytes": archive_bytes,
        "archive_mb": round(archive_bytes / 1e6, 1),
        "n_images": n_images,
        # the single-request figures at the top level, as before
        **{k: v for k, v in single.items()},
        "target_peak_rss_mb": TARGET_PEAK_RSS_MB,
        "resumable": {**resumable, "chunk_mb": chunk_mb},
        "resumable_to_single_throughput": round(ratio, 3),
        "resumable_within_20_percent": ratio >= 0.8,
        "notes": "peak_rss_mb is VmHWM of the uvicorn process over its whole life "
        "(start-up included), a fresh process per mode; each time covers transfer, "
        "storing, member-by-member extraction, validation (JPEG decode at 1/8 scale) and "
        "the database write; the resumable one also the server's SHA-256 check of the whole "
        "archive (the client's SHA-256 is computed beforehand, as pack_capture does)",
        "load_average": os.getloadavg(),
        "machine": {
            "python": platform.python_version(),
            "cpus": os.cpu_count(),
            "platform": platform.platform(),
        },
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size-mb", type=int, default=1024)
    parser.add_argument("--out", type=Path, default=REPO_ROOT / "bench/results/upload.json")
    parser.add_argument("--workdir", type=Path, default=None, help="default: a temp folder")
    parser.add_argument("--chunk-mb", type=int, default=64, help="resumable PATCH size, MiB")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="upload-bench-", dir=args.workdir) as tmp:
        result = run(args.size_mb, args.out, Path(tmp), args.chunk_mb)
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
