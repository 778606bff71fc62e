"""Structure from motion: our stage (pycolmap, in-process) vs the COLMAP command line.

    python -m bench.colmap_bench [--scene DIR] [--work DIR]

The same 30 generated views at 800×600 (synth 'moved', demo preset, seed 1), the same
intrinsics held fixed and the same feature budget, CPU only, both in the same run:
our ``run_sfm`` (features, exhaustive matching, incremental mapping) against
``colmap feature_extractor`` / ``exhaustive_matcher`` / ``mapper`` with
``--SiftExtraction.use_gpu 0 --SiftMatching.use_gpu 0``. Writes
``bench/results/reconstruct_colmap.json`` with per-step wall times and the ratio.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from workers.pipeline.reconstruct import options_from_preset, parse_cameras
from workers.pipeline.reconstruct.common import list_images
from workers.pipeline.reconstruct.sfm import run_sfm
from workers.pipeline.synth import generate, preset

ROOT = Path(__file__).resolve().parents[1]
TMP = Path(os.environ.get("TWINDELTA_BENCH_TMP", "/tmp/twindelta_bench"))


def ours(images: Path, work: Path, cameras_raw: dict[str, Any]) -> dict[str, Any]:
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    options = options_from_preset("default")
    steps: dict[str, float] = {}
    current: list[Any] = [None, 0.0]

    def progress(stage: str, _fraction: float) -> None:
        now = time.perf_counter()
        if stage != current[0]:
            if current[0] is not None:
                steps[current[0]] = steps.get(current[0], 0.0) + now - current[1]
            current[0], current[1] = stage, now

    t0 = time.perf_counter()
    names = list_images(images)
    sparse = run_sfm(images, work, names, options, parse_cameras(cameras_raw), progress)
    total = time.perf_counter() - t0
    progress("done", 1.0)
    return {
        "steps_s": {k: round(v, 2) for k, v in steps.items()},
        "total_s": round(total, 2),
        "registered": len(sparse.views),
        "images": len(names),
        "points": len(sparse.points),
        "mean_reprojection_error_px": sparse.mean_reprojection_error_px,
        "max_num_features": options.max_num_features,
    }


def colmap_cli(exe: str, images: Path, work: Path, cameras_raw: dict[str, Any]) -> dict[str, Any]:
    shutil.rmtree(work, ignore_errors=True)
    (work / "sparse").mkdir(parents=True)
    intr = cameras_raw["intrinsics"]
    params = ",".join(f"{v:.6f}" for v in intr["params"])
    db = str(work / "database.db")
    env = {**os.environ, "QT_QPA_PLATFORM": "offscreen"}
    steps = {
        "features": [
            exe, "feature_extractor", "--database_path", db, "--image_path", str(images),
            "--ImageReader.single_camera", "1", "--ImageReader.camera_model", intr["model"],
            "--ImageReader.camera_params", params, "--SiftExtraction.use_gpu", "0",
            "--SiftExtraction.max_num_features", "4096",
        ],
        "matching": [
            exe, "exhaustive_matcher", "--database_path", db, "--SiftMatching.use_gpu", "0",
        ],
        "mapping": [
            exe, "mapper", "--database_path", db, "--image_path", str(images),
            "--output_path", str(work / "sparse"), "--Mapper.ba_refine_focal_length", "0",
            "--Mapper.ba_refine_principal_point", "0", "--Mapper.ba_refine_extra_params", "0",
        ],
    }  # fmt: skip
    times: dict[str, float] = {}
    for name, cmd in steps.items():
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=1800)
        times[name] = round(time.perf_counter() - t0, 2)
        if proc.returncode != 0:
            raise RuntimeError(f"colmap {name} exit {proc.returncode}: {proc.stderr[-600:]}")
    registered = None
    model = work / "sparse" / "0"
    if model.is_dir():
        import pycolmap

        registered = pycolmap.Reconstruction(str(model)).num_reg_images()
    version = subprocess.run([exe, "help"], env=env, capture_output=True, text=True).stdout
    return {
        "steps_s": times,
        "total_s": round(sum(times.values()), 2),
        "registered": registered,
        "version": version.splitlines()[0] if version else None,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", type=Path, default=TMP / "colmap" / "scene")
    parser.add_argument("--work", type=Path, default=TMP / "colmap")
    parser.add_argument(
        "--out", type=Path, default=ROOT / "bench" / "results" / "reconstruct_colmap.json"
    )
    parser.add_argument("--quick", action="store_true", help="accepted; the run is the same")
    args = parser.parse_args(argv)
    if not (args.scene / "ground_truth.json").is_file():
        generate(args.scene, "moved", 1, preset("demo"))
    images = args.scene / "before" / "images"
    cameras_raw = json.loads((args.scene / "before" / "cameras.json").read_text())
    cameras_raw = {"intrinsics": cameras_raw["intrinsics"]}
    report: dict[str, Any] = {
        "what": "SfM on 30 views 800×600: our pycolmap stage vs the COLMAP CLI (CPU)",
        "cpus": os.cpu_count(),
        "load_average": os.getloadavg(),
    }
    report["ours"] = ours(images, args.work / "ours", cameras_raw)
    print("ours", report["ours"], flush=True)
    exe = shutil.which("colmap")
    if exe is None:
        report["colmap_cli"] = "skipped: colmap not installed (apt-get install colmap)"
    else:
        try:
            report["colmap_cli"] = colmap_cli(exe, images, args.work / "cli", cameras_raw)
            report["ratio_cli_over_ours"] = round(
                report["colmap_cli"]["total_s"] / report["ours"]["total_s"], 2
            )
        except (RuntimeError, subprocess.TimeoutExpired) as exc:
            report["colmap_cli"] = f"failed: {exc}"
        print("colmap", report["colmap_cli"], flush=True)
    report["load_average_end"] = os.getloadavg()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=1, default=float))
    return 0 if isinstance(report.get("colmap_cli"), dict) or exe is None else 1


if __name__ == "__main__":
    raise SystemExit(main())
