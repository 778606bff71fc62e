"""Upload benchmark: a ~1 GB snapshot archive through the real API process.

``python bench/upload_bench.py [--size-mb 1024] [--out bench/results/upload.json]``

Builds a stored (uncompressed) zip of random-noise JPEGs (incompressible, so the bytes on
the wire are the bytes stored; a few distinct images repeated under different names) with
one YOLO label file per image, starts the API as production does
(``uvicorn app.main:create_app --factory``, embedded SQLite, a temporary data folder,
a bootstrap admin key) on a free port, creates an environment, streams the archive from
disk with httpx, and records wall time, throughput and the API process's peak resident
memory (``VmHWM`` from ``/proc/<pid>/status``) against the 300 MB target.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import platform
import secrets
import subprocess
import sys
import tempfile
import threading
import time
import zipfile
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from PIL import Image

from app.client import free_port

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


def run(size_mb: int, out: Path, workdir: Path) -> dict[str, Any]:
    archive = workdir / "capture.zip"
    t0 = time.perf_counter()
    archive_bytes, n_images = build_archive(archive, size_mb * 1024**2)
    build_s = time.perf_counter() - t0
    print(f"archive: {archive_bytes / 1e6:.0f} MB, {n_images} images ({build_s:.1f} s)")

    data_dir = workdir / "data"
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
    try:
        with httpx.Client(base_url=base, timeout=None) as client:
            for _ in range(600):
                try:
                    if client.get("/healthz").status_code == 200:
                        break
                except httpx.TransportError:
                    pass
                time.sleep(0.1)
            headers = {"Authorization": f"Bearer {admin_key}"}
            r = client.post(
                "/v1/environments", json={"name": "bench", "classes": CLASSES}, headers=headers
            )
            r.raise_for_status()
            env_id = r.json()["id"]
            idle_rss_kb = proc_status_kb(server.pid, "VmRSS")
            idle_hwm_kb = proc_status_kb(server.pid, "VmHWM")
            sampler = RssSampler(server.pid)
            sampler.start()
            t0 = time.perf_counter()
            with archive.open("rb") as fh:  # httpx streams file objects in chunks
                r = client.post(
                    f"/v1/environments/{env_id}/snapshots",
                    files={"archive": ("capture.zip", fh, "application/zip")},
                    headers=headers,
                )
            seconds = time.perf_counter() - t0
            sampler.stop.set()
            sampler.join()
            peak_kb = proc_status_kb(server.pid, "VmHWM")
        if r.status_code != 202:
            raise SystemExit(f"upload failed: {r.status_code} {r.text[:500]}")
        snap = r.json()["snapshot"]
    finally:
        server.terminate()
        server.wait(30)
    result: dict[str, Any] = {
        "benchmark": "snapshot upload, one stored zip through the API process",
        "archive_bytes": archive_bytes,
        "archive_mb": round(archive_bytes / 1e6, 1),
        "n_images": n_images,
        "n_detections": snap["n_detections"],
        "status": r.status_code,
        "seconds": round(seconds, 2),
        "mb_per_s": round(archive_bytes / 1e6 / seconds, 1),
        "peak_rss_mb": round(peak_kb / 1024, 1),
        "idle_rss_mb": round(idle_rss_kb / 1024, 1),
        "idle_hwm_mb": round(idle_hwm_kb / 1024, 1),
        "max_sampled_rss_mb": round(max((kb for _, kb in sampler.samples), default=0) / 1024, 1),
        "target_peak_rss_mb": TARGET_PEAK_RSS_MB,
        "within_target": peak_kb / 1024 <= TARGET_PEAK_RSS_MB,
        "notes": "peak_rss_mb is VmHWM of the uvicorn process over its whole life "
        "(start-up included); the time covers transfer, multipart spooling, member-by-member "
        "extraction, validation (JPEG decode at 1/8 scale) and the database write",
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
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="upload-bench-", dir=args.workdir) as tmp:
        result = run(args.size_mb, args.out, Path(tmp))
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
