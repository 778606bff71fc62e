"""Cost of the reconstruct stage at real capture sizes: photos → fused cloud.

    python bench/capture_bench.py [--series photos,resolution,policy,matching,target]
        [--out bench/results/capture.json]

A capture is ``n`` photos at ``width``×``height`` (4:3) of the "moved" scene's before capture
(seed 1, the demo look: noise σ 1.5, JPEG 92). Photos are rendered once per (views, size) as a
master capture under ``bench/.cache/capture``; a capture of fewer photos takes the master's
views evenly spaced round the ring, one of a smaller size is the master's photos resampled
(INTER_AREA, K scaled with pixel centres kept). Each run calls the worker's reconstruct stage
(``workers.pipeline.reconstruct.reconstruct``: photos in a folder → cloud.ply, as the worker
runs it after its inputs are fetched; upload and storage are not in the figure) in a child
process and records wall time, the child's peak RSS (``ru_maxrss`` of RUSAGE_CHILDREN), the
stage timings, images registered and the cloud's distance to the true surfaces (median, p95)
and completeness within 1 cm of the visible room (``reconstruct_bench.cloud_metrics``).
Growth exponents are least-squares slopes of log(time) and log(RSS) on log(photos) or
log(pixels).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from workers.pipeline.reconstruct.common import read_image

ROOT = Path(__file__).resolve().parents[1]
CACHE = ROOT / "bench" / ".cache" / "capture"
SIZES: dict[str, tuple[int, int]] = {
    "1MP": (1152, 864),
    "4MP": (2304, 1728),
    "12MP": (4000, 3000),
}
SCENARIO, SEED = "moved", 1
FOCAL_PER_WIDTH = 650.0 / 800.0  # the synth default's field of view at every size


def master_capture(n_views: int, size: str) -> Path:
    """Render (once) the before capture of ``n_views`` photos at ``SIZES[size]``; returns the
    scene folder (reference.json, ground_truth.json, objects/, before/images, cameras.json)."""
    from workers.pipeline.synth import PRESETS, CameraOptions, PathOptions, ground_truth
    from workers.pipeline.synth.generate import write_capture
    from workers.pipeline.synth.scene import build_scenario
    from workers.pipeline.synth.shapes import builtin_models, write_model_ply

    width, height = SIZES[size]
    folder = CACHE / f"master_{n_views}v_{size}"
    if (folder / "done").exists():
        return folder
    options = replace(
        PRESETS["demo"],
        camera=CameraOptions(width, height, FOCAL_PER_WIDTH * width),
        path=PathOptions(n_views=n_views),
    )
    built = build_scenario(SCENARIO, builtin_models(), SEED, options)
    folder.mkdir(parents=True, exist_ok=True)
    for model in built.models:
        write_model_ply(model, folder / "objects" / f"{model.name}.ply")
    (folder / "reference.json").write_text(json.dumps(built.markers.reference(), indent=1))
    (folder / "ground_truth.json").write_text(json.dumps(ground_truth(built, options), indent=1))
    t = time.perf_counter()
    write_capture(built, "before", options, folder)
    (folder / "done").write_text(f"rendered in {time.perf_counter() - t:.0f} s\n")
    return folder


def capture(master: Path, n_photos: int, size: str) -> Path:
    """A capture of ``n_photos`` of ``master``'s views (evenly spaced) at ``SIZES[size]``:
    ``<folder>/images`` and ``<folder>/cameras.json`` (intrinsics and true poses)."""
    width, height = SIZES[size]
    folder = CACHE / f"{master.name}__{n_photos}p_{size}"
    raw = json.loads((master / "before" / "cameras.json").read_text())
    poses = json.loads((master / "ground_truth.json").read_text())["camera_poses"]["before"]
    names = sorted(poses)
    picked = [names[round(i * len(names) / n_photos)] for i in range(n_photos)]
    intr = dict(raw["intrinsics"])
    s = width / intr["width"]
    fx, fy, cx, cy = intr["params"][:4]
    intr.update(
        width=width,
        height=height,
        params=[fx * s, fy * s, (cx + 0.5) * s - 0.5, (cy + 0.5) * s - 0.5],
    )
    cams = {"intrinsics": intr, "poses": {n: poses[n] for n in picked}}
    if (folder / "cameras.json").exists():
        return folder
    images = folder / "images"
    shutil.rmtree(folder, ignore_errors=True)
    images.mkdir(parents=True)
    for name in picked:
        src = master / "before" / "images" / name
        if s == 1.0:
            (images / name).symlink_to(src)
            continue
        img = read_image(src)
        small = cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(images / name), small, [cv2.IMWRITE_JPEG_QUALITY, 92])
    (folder / "cameras.json").write_text(json.dumps(cams, indent=1))
    return folder


def run_one(folder: Path, master: Path, work: Path, overrides: dict[str, Any]) -> dict[str, Any]:
    """Reconstruct ``folder``'s capture in this process (the child of :func:`run_child`) and
    score it: seconds, peak RSS (MiB) at the end of the stage, quality and cloud metrics."""
    from bench.reconstruct_bench import visible_surface_samples
    from workers.pipeline.reconstruct import options_from_preset, parse_cameras, reconstruct
    from workers.pipeline.reconstruct.fusion import read_ply
    from workers.pipeline.synth import load_true_surfaces

    raw = json.loads((folder / "cameras.json").read_text())
    reference = json.loads((master / "reference.json").read_text())
    options = options_from_preset("default", **overrides)
    shutil.rmtree(work, ignore_errors=True)
    t = time.perf_counter()
    res = reconstruct(
        folder / "images",
        work,
        options,
        parse_cameras({"intrinsics": raw["intrinsics"]}),
        reference,
    )
    seconds = time.perf_counter() - t
    rss_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    cloud, _ = read_ply(res.cloud_path)
    meshes = load_true_surfaces(master, "before")
    return {
        "reconstruct_s": round(seconds, 1),
        "peak_rss_mib": round(rss_mib),
        "images_registered": res.quality["images_registered"],
        "timings_s": res.quality["timings_s"],
        **cloud_scores(cloud, meshes, visible_surface_samples(meshes, raw).points),
    }


def cloud_scores(cloud: np.ndarray, meshes: dict[str, Any], visible: np.ndarray) -> dict[str, Any]:
    """Distances (m) of the (M, 3) cloud to the true surfaces and the share of the (N, 3)
    visible true-surface samples with a cloud point within 1 cm."""
    import open3d as o3d
    from scipy.spatial import cKDTree

    from bench.reconstruct_bench import _scene

    dist = _scene(meshes).compute_distance(o3d.core.Tensor(cloud.astype(np.float32))).numpy()  # type: ignore[call-overload]
    nn, _ = cKDTree(cloud).query(visible, k=1, workers=2)
    return {
        "points": len(cloud),
        "distance_median_m": float(np.median(dist)),
        "distance_p95_m": float(np.percentile(dist, 95)),
        "completeness_1cm": float(np.mean(nn < 0.01)),
    }


def work_folder(name: str) -> Path:
    """Where run ``name`` leaves its work (the child's reconstruction, the service's cloud)."""
    return Path(os.environ.get("TWINDELTA_BENCH_TMP", "/tmp/twindelta_bench")) / "capture" / name


def run_child(
    name: str, n_photos: int, size: str, master: Path, overrides: dict[str, Any]
) -> dict[str, Any]:
    """One run in a fresh child process (its own peak RSS); the run's row of capture.json."""
    folder = capture(master, n_photos, size)
    work = work_folder(name)
    spec = json.dumps(
        {"folder": str(folder), "master": str(master), "work": str(work), "overrides": overrides}
    )
    load = os.getloadavg()[0]
    t = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", "bench.capture_bench", "--child", spec],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    wall = time.perf_counter() - t
    width, height = SIZES[size]
    row: dict[str, Any] = {
        "photos": n_photos,
        "size": f"{width}x{height}",
        "megapixels": round(width * height / 1e6, 2),
        "overrides": overrides,
        "load_average_1m": [round(load, 2), round(os.getloadavg()[0], 2)],
        "child_wall_s": round(wall, 1),
    }
    if proc.returncode != 0:
        row["error"] = proc.stderr[-2000:]
    else:
        row.update(json.loads(proc.stdout.strip().splitlines()[-1]))
    print(name, json.dumps(row), flush=True)
    return row


def _tree_rss_mib(root_pid: int) -> tuple[float, float]:
    """(largest process, whole tree) resident memory in MiB of ``root_pid`` and every
    descendant, read from /proc; processes that end while read are skipped."""
    from bench.upload_bench import proc_status_kb

    parent: dict[int, int] = {}
    rss: dict[int, float] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        pid = int(stat.parent.name)
        try:
            parent[pid] = int(stat.read_text().rsplit(")", 1)[1].split()[1])
            rss[pid] = proc_status_kb(pid, "VmRSS") / 1024
        except (OSError, KeyError):  # ended, or a kernel thread (no VmRSS)
            continue
    tree, frontier = {root_pid}, [root_pid]
    while frontier:
        kids = [pid for pid, ppid in parent.items() if ppid in frontier and pid not in tree]
        tree.update(kids)
        frontier = kids
    sizes = [rss.get(pid, 0.0) for pid in tree]
    return max(sizes), sum(sizes)


def run_service(name: str, master: Path) -> dict[str, Any]:
    """Upload ``master``'s before capture (all its photos, at its size) to the embedded
    service (``twindelta serve``: SQLite, local folder, one CPU worker) as a capture station
    does (tar, resumable upload) and wait for the snapshot job: seconds from the start of the
    upload to the fused cloud recorded, the service tree's peak RSS (sampled every 0.5 s) and
    the recorded cloud scored against the true surfaces."""
    import tempfile
    import threading

    import httpx

    from app.client import Client, check, embedded_service, poll_job
    from bench.reconstruct_bench import visible_surface_samples
    from workers.pipeline.reconstruct.fusion import read_ply
    from workers.pipeline.synth import load_true_surfaces

    capture_dir = master / "before"
    raw = json.loads((capture_dir / "cameras.json").read_text())
    admin = "td_bench_admin_key_0123456789abcdef"
    peak = {"process_mib": 0.0, "tree_mib": 0.0}
    stop = threading.Event()

    def sample() -> None:
        while not stop.wait(0.5):
            largest, total = _tree_rss_mib(os.getpid())
            peak["process_mib"] = max(peak["process_mib"], largest)
            peak["tree_mib"] = max(peak["tree_mib"], total)

    load = os.getloadavg()[0]
    with (
        tempfile.TemporaryDirectory(prefix="capture-service-") as tmp,
        embedded_service(Path(tmp) / "data", admin, Path(tmp) / "serve.log") as client,
    ):
        env = check(
            client.post(
                "/v1/environments",
                json={
                    "name": name,
                    "classes": (capture_dir / "classes.txt").read_text().split(),
                    "reference": json.loads((master / "reference.json").read_text()),
                },
            ),
            201,
        )
        sampler = threading.Thread(target=sample, daemon=True)
        sampler.start()
        t = time.perf_counter()
        with Client(str(client.base_url), admin) as station:
            uploaded = station.upload_capture(env["id"], capture_dir, workdir=Path(tmp))
        upload_s = time.perf_counter() - t
        job = poll_job(client, uploaded.job, name, timeout_s=3 * 3600, quiet=True)
        total_s = time.perf_counter() - t
        stop.set()
        sampler.join()
        snap = check(client.get(f"/v1/snapshots/{uploaded.snapshot}"), 200)
        cloud_file = work_folder(name) / "cloud.ply"  # kept, as run_child's work folder is
        cloud_file.parent.mkdir(parents=True, exist_ok=True)
        with client.stream(
            "GET", f"/v1/snapshots/{uploaded.snapshot}/pointcloud", timeout=httpx.Timeout(600)
        ) as resp:
            resp.raise_for_status()
            with cloud_file.open("wb") as fh:
                for chunk in resp.iter_bytes(1 << 20):
                    fh.write(chunk)
        cloud, _ = read_ply(cloud_file)
    if job["state"] != "succeeded":
        raise RuntimeError(f"{name}: snapshot job {job['state']}: {job.get('error')}")
    meshes = load_true_surfaces(master, "before")
    width, height = raw["intrinsics"]["width"], raw["intrinsics"]["height"]
    truth = json.loads((master / "ground_truth.json").read_text())
    seen_from = {"intrinsics": raw["intrinsics"], "poses": truth["camera_poses"]["before"]}
    quality = snap["quality"]
    row: dict[str, Any] = {
        "photos": len(list((capture_dir / "images").iterdir())),
        "size": f"{width}x{height}",
        "megapixels": round(width * height / 1e6, 2),
        "load_average_1m": [round(load, 2), round(os.getloadavg()[0], 2)],
        "upload_s": round(upload_s, 1),
        "upload_to_cloud_s": round(total_s, 1),
        "job_s": _seconds_between(job["started_at"], job["finished_at"]),
        "queued_s": _seconds_between(job["created_at"], job["started_at"]),
        "peak_rss_mib": round(peak["process_mib"]),
        "peak_rss_service_tree_mib": round(peak["tree_mib"]),
        "images_registered": quality.get("images_registered"),
        "timings_s": quality.get("timings_s"),
        **cloud_scores(cloud, meshes, visible_surface_samples(meshes, seen_from).points),
    }
    print(name, json.dumps(row), flush=True)
    return row


def _seconds_between(start: str, end: str) -> float:
    from datetime import datetime

    return round((datetime.fromisoformat(end) - datetime.fromisoformat(start)).total_seconds(), 1)


def slope(xs: list[float], ys: list[float]) -> float | None:
    """Least-squares slope of log(y) on log(x); None with fewer than two points."""
    if len(xs) < 2:
        return None
    return float(np.polyfit(np.log(xs), np.log(ys), 1)[0])


def exponents(runs: dict[str, dict[str, Any]], prefix: str, key: str) -> dict[str, Any]:
    """Growth exponents of time and peak RSS in ``key`` over the runs named ``prefix*``."""
    rows = [r for n, r in runs.items() if n.startswith(prefix) and "error" not in r]
    xs = [float(r[key]) for r in rows]
    return {
        "over": key,
        "runs": sorted(n for n in runs if n.startswith(prefix)),
        "time_exponent": slope(xs, [r["reconstruct_s"] for r in rows]),
        "rss_exponent": slope(xs, [r["peak_rss_mib"] for r in rows]),
    }


def plan(
    series: list[str], quick: bool
) -> list[tuple[str, int, str, tuple[int, str], dict[str, Any]]]:
    """(run name, photos, size, master (views, size), overrides) of every requested run."""
    ring, sharp, target = (200, "1MP"), (30, "12MP"), (100, "12MP")
    runs: list[tuple[str, int, str, tuple[int, str], dict[str, Any]]] = []
    if quick:  # a smoke run: 30 photos of a 30-view 1 MP render (about 40 s to render)
        return [("photos_30_1MP", 30, "1MP", (30, "1MP"), {})]
    if "photos" in series:
        for n in (30, 60, 100, 200):
            runs.append((f"photos_{n}_1MP", n, "1MP", ring, {}))
    if "resolution" in series:
        for size in ("1MP", "4MP", "12MP"):
            runs.append((f"resolution_30_{size}", 30, size, sharp, {}))
    if "policy" in series:
        for sift, dense in ((1600, 1600), (1600, 2304), (1152, 1152), (2304, 1152)):
            runs.append(
                (
                    f"policy_12MP_sift{sift}_mvs{dense}",
                    30,
                    "12MP",
                    sharp,
                    {"max_image_size": sift, "mvs_max_image_size": dense},
                )
            )
    if "matching" in series:
        runs.append(
            ("matching_100_1MP_sequential_no_loops", 100, "1MP", ring, {"loop_neighbours": 0})
        )
        runs.append(
            ("matching_100_1MP_exhaustive", 100, "1MP", ring, {"exhaustive_max_images": 100})
        )
    if "target" in series:
        runs.append(("target_100_12MP", 100, "12MP", target, {}))
    if "service" in series:  # through the HTTP API and a worker: upload to fused cloud
        runs.append(("service_100_12MP", 100, "12MP", target, {}))
    return runs


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--series", default="photos,resolution,policy,matching,target,service")
    parser.add_argument("--only", default="", help="comma-separated run names (a subset)")
    parser.add_argument("--quick", action="store_true", help="30 photos at 1 MP only (a smoke run)")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "capture.json")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        spec = json.loads(args.child)
        row = run_one(
            Path(spec["folder"]), Path(spec["master"]), Path(spec["work"]), spec["overrides"]
        )
        print(json.dumps(row))
        return 0
    results: dict[str, Any] = json.loads(args.out.read_text()) if args.out.exists() else {}
    runs: dict[str, dict[str, Any]] = results.setdefault("runs", {})
    only = set(filter(None, args.only.split(",")))
    for name, n, size, (views, master_size), overrides in plan(args.series.split(","), args.quick):
        if only and name not in only:
            continue
        master = master_capture(views, master_size)
        if name.startswith("service_"):
            runs[name] = run_service(name, master)
        else:
            runs[name] = run_child(name, n, size, master, overrides)
        results["growth"] = {
            "photos_at_1MP": exponents(runs, "photos_", "photos"),
            "pixels_at_30_photos": exponents(runs, "resolution_30_", "megapixels"),
        }
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
