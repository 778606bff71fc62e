"""C2C speed and agreement against CloudCompare, and the whole compare stage at 1M points.

    python -m bench.c2c_bench [--quick] [--points 1000000] [--runs 3]

Two clouds of about ``--points`` points each are sampled (area-uniform, 1 mm noise, seeded)
from the true surfaces (room, markers' floor, objects) of a generated 'multiple' scene's
before and after captures; coordinates are rounded to float32 first, as CloudCompare
stores them, so both tools see the same numbers. Our ``workers.pipeline.compare.c2c``
(SciPy cKDTree, all cores) runs both ways, the median of ``--runs`` runs each, against
``CloudCompare -SILENT -C2C_DIST`` on the same PLY files (wall time of the command, so it
includes reading the files; its own printed mean/std is compared with ours). Then the whole
compare stage (no pose) on those clouds with 30 cameras per capture and detector boxes from
the objects' projected extents. Writes ``bench/results/c2c.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from workers.pipeline.compare.c2c import c2c
from workers.pipeline.compare.data import Camera, CaptureData, TwinInstance
from workers.pipeline.compare.options import options_from_json
from workers.pipeline.compare.stage import compare_snapshots
from workers.pipeline.synth import PRESETS, build_scenario, builtin_models, true_surfaces
from workers.pipeline.synth.cameras import intrinsics_matrix
from workers.pipeline.synth.generate import capture_path

ROOT = Path(__file__).resolve().parents[1]
TMP = Path(os.environ.get("TWINDELTA_BENCH_TMP", "/tmp/twindelta_bench"))
CC_MEAN = re.compile(r"Mean distance\s*=\s*([-+0-9.eE]+)\s*/\s*std deviation\s*=\s*([-+0-9.eE]+)")
COMPARE_TARGET_S = 10.0


def sample_clouds(n: int, seed: int) -> tuple[Any, dict[str, np.ndarray], list[str]]:
    """(scenario, {"before", "after"} → (n, 3) float64 of float32-exact values, classes)."""
    scenario = build_scenario("multiple", builtin_models(), seed, PRESETS["demo"])
    rng = np.random.default_rng(seed)
    clouds = {}
    for capture in ("before", "after"):
        merged = o3d.geometry.TriangleMesh()
        for mesh in true_surfaces(scenario, capture).values():
            merged += mesh
        o3d.utility.random.seed(seed + len(clouds))
        pts = np.asarray(merged.sample_points_uniformly(n).points)
        pts = pts + rng.normal(scale=0.001, size=pts.shape)
        clouds[capture] = pts.astype(np.float32).astype(np.float64)
    return scenario, clouds, [m.name for m in scenario.models]


def write_ply(path: Path, points: np.ndarray) -> None:
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    o3d.io.write_point_cloud(str(path), pcd, write_ascii=False)


def ours(compared: np.ndarray, reference: np.ndarray, runs: int) -> dict[str, Any]:
    times, dist = [], np.zeros(0)
    for _ in range(runs):
        t0 = time.perf_counter()
        dist = c2c(compared, reference)
        times.append(time.perf_counter() - t0)
    return {
        "seconds": [round(t, 3) for t in times],
        "median_s": round(statistics.median(times), 3),
        "mean_m": float(dist.mean()),
        "std_m": float(dist.std()),
    }


def cloudcompare(
    exe: str, compared: Path, reference: Path, runs: int, work: Path
) -> dict[str, Any]:
    """Wall time of CloudCompare's C2C (file loading included) and its printed mean/std."""
    times: list[float] = []
    mean = std = None
    env = {**os.environ, "QT_QPA_PLATFORM": "offscreen"}
    for _ in range(runs):
        cmd = [exe, "-SILENT", "-NO_TIMESTAMP", "-C_EXPORT_FMT", "PLY"]
        cmd += ["-O", str(compared), "-O", str(reference), "-C2C_DIST"]
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, cwd=work, env=env, capture_output=True, text=True, timeout=900)
        times.append(time.perf_counter() - t0)
        found = CC_MEAN.findall(proc.stdout + proc.stderr)
        if proc.returncode != 0 or not found:
            tail = (proc.stdout + proc.stderr)[-800:]
            raise RuntimeError(f"CloudCompare exit {proc.returncode}: {tail}")
        mean, std = float(found[-1][0]), float(found[-1][1])
    t_load = _cc_load_only(exe, compared, reference, work, env)
    return {
        "seconds": [round(t, 3) for t in times],
        "median_s": round(statistics.median(times), 3),
        "load_only_s": round(t_load, 3),
        "median_minus_load_s": round(statistics.median(times) - t_load, 3),
        "mean_m": mean,
        "std_m": std,
    }


def _cc_load_only(exe: str, a: Path, b: Path, work: Path, env: dict[str, str]) -> float:
    """Wall time of CloudCompare opening both files and doing nothing (start-up + I/O)."""
    t0 = time.perf_counter()
    subprocess.run(
        [exe, "-SILENT", "-NO_TIMESTAMP", "-O", str(a), "-O", str(b)],
        cwd=work,
        env=env,
        capture_output=True,
        timeout=900,
    )
    return time.perf_counter() - t0


def cameras_and_boxes(
    scenario: Any, capture: str, classes: list[str]
) -> tuple[tuple[Camera, ...], dict[str, np.ndarray]]:
    """The capture's 30 true cameras and, per image, YOLO rows from each object's projected
    vertex extent (no occlusion: enough for timing the stage)."""
    options = PRESETS["demo"]
    k = intrinsics_matrix(options.camera)
    w, h = options.camera.width, options.camera.height
    cams, dets = [], {}
    for i, env_from_cam in enumerate(capture_path(scenario, capture, options)):
        name = f"view_{i:03d}.png"
        cam_from_env = np.linalg.inv(env_from_cam)
        cams.append(Camera(name, k, w, h, cam_from_env))
        rows = []
        for p in scenario.capture(capture):
            v = p.model.mesh.vertices @ p.env_from_object[:3, :3].T + p.env_from_object[:3, 3]
            pc = v @ cam_from_env[:3, :3].T + cam_from_env[:3, 3]
            if np.any(pc[:, 2] <= 0.05):
                continue
            uv = (pc @ k.T)[:, :2] / pc[:, 2:3]
            x0, y0 = np.clip(uv.min(axis=0), 0, [w, h])
            x1, y1 = np.clip(uv.max(axis=0), 0, [w, h])
            if x1 - x0 < 4 or y1 - y0 < 4:
                continue
            cid = classes.index(p.model.name)
            rows.append(
                [cid, (x0 + x1) / 2 / w, (y0 + y1) / 2 / h, (x1 - x0) / w, (y1 - y0) / h, 0.9]
            )
        dets[name] = np.asarray(rows, dtype=np.float64).reshape(-1, 6)
    return tuple(cams), dets


def compare_stage(
    scenario: Any, clouds: dict[str, np.ndarray], classes: list[str], runs: int
) -> dict[str, Any]:
    captures = {}
    for capture in ("before", "after"):
        cams, dets = cameras_and_boxes(scenario, capture, classes)
        captures[capture] = CaptureData(points_env=clouds[capture], cameras=cams, detections=dets)
    diameters = {
        m.name: float(np.linalg.norm(np.ptp(m.mesh.vertices, axis=0))) for m in scenario.models
    }
    twin = [
        TwinInstance(p.instance_id, p.model.name, p.env_from_object)
        for p in scenario.capture("before")
    ]
    times, stage_timings, result = [], [], None
    for _ in range(runs):
        t0 = time.perf_counter()
        result = compare_snapshots(
            captures["before"],
            captures["after"],
            twin,
            classes,
            diameters,
            options_from_json("default"),
        )
        times.append(time.perf_counter() - t0)
        stage_timings.append(result.stats["timings_s"])
    assert result is not None
    median = statistics.median(times)
    return {
        "points": {k: len(v) for k, v in clouds.items()},
        "cameras_per_capture": len(captures["after"].cameras),
        "seconds": [round(t, 3) for t in times],
        "median_s": round(median, 3),
        "stage_timings_s": stage_timings,
        "clusters": len(result.clusters),
        "changes": [{"type": c.type, "object": c.object_name} for c in result.changes],
        "truth": [{"type": c["type"], "object": c["object"]} for c in scenario.changes],
        "target_s": COMPARE_TARGET_S,
        "verdict": "met" if median <= COMPARE_TARGET_S else "not met",
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="1 run each instead of 3")
    parser.add_argument("--points", type=int, default=1_000_000)
    parser.add_argument("--runs", type=int, default=None)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--work", type=Path, default=TMP / "c2c")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "c2c.json")
    args = parser.parse_args(argv)
    runs = args.runs or (1 if args.quick else 3)
    args.work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    scenario, clouds, classes = sample_clouds(args.points, args.seed)
    paths = {k: args.work / f"{k}.ply" for k in clouds}
    for k, p in paths.items():
        write_ply(p, clouds[k])
    report: dict[str, Any] = {
        "what": "C2C nearest-neighbour distances, ours vs CloudCompare; whole compare stage",
        "points": {k: len(v) for k, v in clouds.items()},
        "runs": runs,
        "cpus": os.cpu_count(),
        "load_average": os.getloadavg(),
        "prepare_s": round(time.perf_counter() - t0, 1),
        "directions": {},
    }
    exe = shutil.which("CloudCompare") or shutil.which("cloudcompare")
    # "added": distance of every after point to the before cloud; "removed": the reverse
    for direction, (compared, reference) in {
        "added": ("after", "before"),
        "removed": ("before", "after"),
    }.items():
        row: dict[str, Any] = {"compared": compared, "reference": reference}
        row["ours"] = ours(clouds[compared], clouds[reference], runs)
        if exe is None:
            row["cloudcompare"] = (
                "skipped: CloudCompare not installed (apt-get install cloudcompare)"
            )
        else:
            try:
                cc = cloudcompare(exe, paths[compared], paths[reference], runs, args.work)
                row["cloudcompare"] = cc
                row["ratio_cloudcompare_over_ours"] = round(
                    cc["median_s"] / row["ours"]["median_s"], 2
                )
                row["ratio_cloudcompare_minus_load_over_ours"] = round(
                    cc["median_minus_load_s"] / row["ours"]["median_s"], 2
                )
                # CloudCompare prints 6 significant digits or so; compare at what it gives
                row["mean_abs_difference_m"] = abs(cc["mean_m"] - row["ours"]["mean_m"])
                row["std_abs_difference_m"] = abs(cc["std_m"] - row["ours"]["std_m"])
                row["agree_within_1e-6_m"] = bool(
                    row["mean_abs_difference_m"] <= 1e-6 and row["std_abs_difference_m"] <= 1e-6
                )
            except (RuntimeError, subprocess.TimeoutExpired) as exc:
                row["cloudcompare"] = f"failed: {exc}"
        report["directions"][direction] = row
        print(direction, json.dumps(row, default=float), flush=True)
    report["compare_stage"] = compare_stage(scenario, clouds, classes, runs)
    print("compare stage", json.dumps(report["compare_stage"], default=float), flush=True)
    report["load_average_end"] = os.getloadavg()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=1, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
