"""Console load benchmark: how long a 2 M-point snapshot takes to open in the console's 3D
view, with the decimated cloud endpoint and with the full PLY as the baseline.

``python -m bench.console_bench [--points 2000000] [--runs 3] [--max-points 300000]
[--out bench/results/console.json]``

Builds the console (npm) when it is missing or stale, starts the embedded service
(``twindelta serve``: SQLite, the real workers) serving it at /ui/, creates an environment
and uploads a generated 2 M-point binary PLY as a laser scan (``POST .../scans``, frame the
identity): the real scan job reads it into the environment frame. Its points lie on a
5 mm grid (floor and four walls), twice the scan stage's 2.5 mm voxel, so the stored cloud
keeps every one. Then headless Chromium (Debian's, software WebGL) opens
``/ui/#/environments/{id}`` in a fresh page per run with the key already in sessionStorage
and reads ``window.__twindelta.cloudReadyMs``: milliseconds from navigation start to the
first frame drawn with the cloud (fetch, parse, upload to WebGL, render). The first
decimated run is the uncached one (the API decimates and caches); the median of ``--runs``
further runs is the figure; the same for the full PLY (``?full=1``). Target: <= 3 s
decimated. Also records the page's own script, gzipped (target < 500 KB)."""

from __future__ import annotations

import argparse
import gzip
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from app.client import check, embedded_service, poll_job
from app.core.export import decimate
from bench.console_browser import CHROMIUM, build_console, chromium, wait_for_cloud

ROOT = Path(__file__).resolve().parents[1]
ADMIN_KEY = "td_console_bench_admin_key_0123456789"
TARGET_S = 3.0
SCRIPT_TARGET_KB = 500
GRID_M = 0.005  # point spacing: twice the scan stage's default 2.5 mm voxel


def room_cloud(n_points: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """At least ``n_points`` (fewer than 0.1 % more) on a square floor and four walls (z up,
    metres, 5 mm grid), coloured like a textured room; (N, 3) float32 and (N, 3) uint8."""
    rng = np.random.default_rng(seed)
    # floor side s and wall height hgt (about s/6) in grid steps: s^2 + 4 s hgt >= n
    side = int(np.ceil(np.sqrt(n_points / (1 + 4 / 6))))
    height = max(1, int(np.ceil((n_points - side * side) / (4 * side))))
    u = (np.arange(side) + 0.5) * GRID_M
    v = (np.arange(height) + 0.5) * GRID_M
    fx, fy = np.meshgrid(u, u, indexing="ij")
    floor = np.stack([fx.ravel(), fy.ravel(), np.zeros(fx.size)], axis=1)
    wu, wz = np.meshgrid(u, v, indexing="ij")
    wu, wz = wu.ravel(), wz.ravel()
    edge = side * GRID_M
    walls = [
        np.stack([wu, np.zeros_like(wu), wz], axis=1),
        np.stack([wu, np.full_like(wu, edge), wz], axis=1),
        np.stack([np.zeros_like(wu), wu, wz], axis=1),
        np.stack([np.full_like(wu, edge), wu, wz], axis=1),
    ]
    xyz = np.concatenate([floor, *walls]) - [edge / 2, edge / 2, 0.0]
    shade = 120 + 60 * np.sin(xyz[:, 0] * 7) * np.cos(xyz[:, 1] * 5) + rng.normal(0, 12, len(xyz))
    rgb = np.clip(np.stack([shade, shade * 0.95, shade * 0.9], axis=1), 0, 255).astype(np.uint8)
    return xyz.astype(np.float32), rgb


def write_ply(path: Path, xyz: np.ndarray, rgb: np.ndarray) -> None:
    """Binary little-endian PLY: float x, y, z and uchar red, green, blue (the layout of the
    API's decimated clouds)."""
    vertex = np.empty(len(xyz), dtype=decimate.RECORD)
    vertex["x"], vertex["y"], vertex["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    vertex["r"], vertex["g"], vertex["b"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    path.write_bytes(decimate.ply_header(len(xyz)) + vertex.tobytes())


def scan_snapshot(client: httpx.Client, ply: Path) -> tuple[str, str, dict[str, Any]]:
    """An environment and a reconstructed scan snapshot of ``ply``: (environment id,
    snapshot id, the snapshot's quality)."""
    env = check(client.post("/v1/environments", json={"name": "bench-2m", "classes": ["box"]}), 201)
    identity = [[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]]
    with ply.open("rb") as f:
        accepted = check(
            client.post(
                f"/v1/environments/{env['id']}/scans",
                files={"file": (ply.name, f, "application/octet-stream")},
                data={"frame": json.dumps({"transform": identity, "units": "m"})},
            ),
            202,
        )
    job = poll_job(client, accepted["job"]["id"], "scan", 1200, quiet=True)
    if job["state"] != "succeeded":
        raise RuntimeError(f"the scan job did not succeed: {job}")
    snapshot = check(client.get(f"/v1/snapshots/{accepted['snapshot']['id']}"), 200)
    return env["id"], snapshot["id"], snapshot["quality"]


def open_times(
    base: str, environment_id: str, runs: int, hash_query: str, timeout_s: float = 120
) -> list[dict[str, Any]]:
    """``runs`` fresh page loads of the environment; each: cloudReadyMs and the points drawn."""
    out = []
    with chromium() as browser:
        for _ in range(runs):
            context = browser.new_context(viewport={"width": 1280, "height": 800})
            context.add_init_script(
                f"sessionStorage.setItem('twindelta.apiKey', {json.dumps(ADMIN_KEY)})"
            )
            page = context.new_page()
            page.goto(f"{base}/ui/#/environments/{environment_id}{hash_query}")
            state = wait_for_cloud(page, timeout_s)
            out.append(
                {
                    "cloud_ready_ms": round(state["cloudReadyMs"], 1),
                    "points_drawn": state["cloudPoints"],
                    "points_total": state["cloudTotalPoints"],
                    "source": state["cloudSource"],
                }
            )
            context.close()
    return out


def script_size(dist: Path) -> dict[str, Any]:
    """The built page's JavaScript, raw and gzipped (level 9), in KB."""
    files = sorted((dist / "assets").glob("*.js"))
    raw = sum(f.stat().st_size for f in files)
    zipped = sum(len(gzip.compress(f.read_bytes(), 9)) for f in files)
    return {
        "files": [f.name for f in files],
        "raw_kb": round(raw / 1024, 1),
        "gzip_kb": round(zipped / 1024, 1),
        "target_gzip_kb": SCRIPT_TARGET_KB,
        "within_target": zipped / 1024 < SCRIPT_TARGET_KB,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=2_000_000)
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--max-points", type=int, default=None, help="the page's default if unset")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "console.json")
    args = parser.parse_args(argv)

    dist = build_console()
    tmp = Path(tempfile.mkdtemp(prefix="console_bench_", dir=os.environ.get("TWINDELTA_BENCH_TMP")))
    xyz, rgb = room_cloud(args.points)
    ply = tmp / "room_2m.ply"
    write_ply(ply, xyz, rgb)
    result: dict[str, Any] = {
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "chromium": CHROMIUM},
        "points_generated": len(xyz),
        "ply_mb": round(ply.stat().st_size / 1e6, 1),
        "runs": args.runs,
        "target_s": TARGET_S,
        "script": script_size(dist),
    }
    query = f"?points={args.max_points}" if args.max_points else ""
    with embedded_service(
        tmp / "data", ADMIN_KEY, tmp / "service.log", console_dir=str(dist)
    ) as client:
        t0 = time.perf_counter()
        env_id, _snapshot, quality = scan_snapshot(client, ply)
        result["scan_job_s"] = round(time.perf_counter() - t0, 1)
        result["snapshot_points"] = quality.get("points")
        base = str(client.base_url).rstrip("/")
        first = open_times(base, env_id, 1, query)[0]  # the API decimates and caches
        decimated = open_times(base, env_id, args.runs, query)
        full = open_times(base, env_id, args.runs, "?full=1" if not query else query + "&full=1")
    med = statistics.median(r["cloud_ready_ms"] for r in decimated)
    med_full = statistics.median(r["cloud_ready_ms"] for r in full)
    result.update(
        {
            "decimated_first_uncached": first,
            "decimated": decimated,
            "decimated_median_ms": med,
            "full": full,
            "full_median_ms": med_full,
            "speedup_full_over_decimated": round(med_full / med, 2),
            "within_target": med / 1000 <= TARGET_S,
            "load_average": os.getloadavg(),
            "at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        }
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    print(json.dumps(result, indent=1))
    return 0 if result["within_target"] else 1


if __name__ == "__main__":
    sys.exit(main())
