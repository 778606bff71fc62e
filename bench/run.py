"""``make bench``: every benchmark, each in its own process, and one summary.

    python -m bench.run [--only poll,c2c] [--quick]

Runs the sub-benchmarks in order (poll, upload, reconstruct on the bench scene and on two
other generated scenes, pose, scenarios, the tuning and test worlds, c2c, colmap, capture
sizes, one worker against two), each as a subprocess so one failure does not lose the
others; records each one's exit status and wall time and writes
``bench/results/summary.json`` with the headline figures of every result file. Before
running, as root, installs the tools some comparisons need (wrk, colmap, cloudcompare) with
apt-get; otherwise says so and records
``"skipped: <why>"`` for exactly the comparisons that need the missing tool.
``--quick`` is a smoke run (fewer scenarios, views, trials and seconds) whose results go
to ``bench/results/quick/`` so they never overwrite a full run's.
Timings depend on the machine's load; every result file records the load average.
Scratch files go under $TWINDELTA_BENCH_TMP (default /tmp/twindelta_bench).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
TMP = os.environ.get("TWINDELTA_BENCH_TMP", "/tmp/twindelta_bench")
LOGS = Path(TMP) / "logs"

# tool → (executable names, Debian package)
TOOLS: dict[str, tuple[tuple[str, ...], str]] = {
    "wrk": (("wrk",), "wrk"),
    "colmap": (("colmap",), "colmap"),
    "cloudcompare": (("CloudCompare", "cloudcompare"), "cloudcompare"),
}


@dataclass(frozen=True)
class Bench:
    """One sub-benchmark: its module, arguments (full and quick), result file and the tools
    without which it is skipped entirely (tools it can do without are handled inside)."""

    name: str
    module: str
    result: str
    args: tuple[str, ...] = ()
    quick_args: tuple[str, ...] = ()
    requires: tuple[str, ...] = ()
    timeout_s: int = 3 * 3600
    headline: Callable[[dict[str, Any]], dict[str, Any]] = field(default=lambda d: {})


def _get(data: Any, *path: Any) -> Any:
    for key in path:
        if isinstance(data, dict):
            data = data.get(key)
        elif isinstance(data, list) and isinstance(key, int) and -len(data) <= key < len(data):
            data = data[key]
        else:
            return None
    return data


def _poll(d: dict[str, Any]) -> dict[str, Any]:
    return {
        r.get("mode", str(i)): {
            "polls_per_s": _get(r, "job_poll", "requests_per_s"),
            "p99_ms": _get(r, "job_poll", "p99_ms"),
            "ratio_to_healthz": r.get("ratio_to_healthz"),
            "meets_target": r.get("meets_target"),
        }
        for i, r in enumerate(d.get("results", []))
    }


def _upload(d: dict[str, Any]) -> dict[str, Any]:
    keys = ("archive_mb", "seconds", "mb_per_s", "peak_rss_mb", "target_peak_rss_mb")
    return {
        **{k: d.get(k) for k in (*keys, "within_target")},
        "resumable": {k: _get(d, "resumable", k) for k in ("seconds", "mb_per_s", "peak_rss_mb")},
        "resumable_to_single_throughput": d.get("resumable_to_single_throughput"),
    }


def _reconstruct(d: dict[str, Any]) -> dict[str, Any]:
    keys = (
        "camera_centre_error_median_m",
        "distance_median_m",
        "distance_p95_m",
        "completeness_1cm",
        "completeness_1cm_work_area",
    )
    return {
        name: {
            **{k: case.get(k) for k in keys},
            "total_s": _get(case, "quality", "timings_s", "total"),
        }
        for name, case in d.get("cases", {}).items()
    }


def _pose(d: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {"ycb_median_s": d.get("ycb_median_s")}
    for key in ("summary", "ycb_summary", "targets", "milk", "threedmatch"):
        value = d.get(key)
        if isinstance(value, dict):
            out[key] = {k: v for k, v in value.items() if not isinstance(v, dict | list)}
    return out


def _scenarios(d: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {"summary": d.get("summary"), "per_scenario": {}}
    for name, run in d.get("scenarios", {}).items():
        if "error" in run:
            out["per_scenario"][name] = run["error"]
            continue
        out["per_scenario"][name] = {
            "clusters_per_threshold": {
                k: v.get("n_clusters") for k, v in run.get("thresholds", {}).items()
            },
            "found": sum(1 for c in run["ours"]["changes"] if c.get("found")),
            "true_changes": len(run["ours"]["changes"]),
            "false_changes": len(run["ours"]["false_changes"]),
            "unidentified": run["ours"].get("unidentified"),
        }
    out["robustness"] = _get(d, "robustness", "summary") or _get(d, "robustness", "error")
    out["clean_detector"] = _get(d, "clean_detector", "summary")
    return out


def _world_set(d: dict[str, Any]) -> dict[str, Any]:
    return {
        "set": d.get("set"),
        **{name: v.get("summary") for name, v in d.get("variants", {}).items()},
    }


def _inventory(d: dict[str, Any]) -> dict[str, Any]:
    summary = d.get("summary") or {}
    return {"set": d.get("set"), **{k: v for k, v in summary.items() if k != "targets"}}


def _c2c(d: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {"points": d.get("points")}
    for name, row in d.get("directions", {}).items():
        cc = row.get("cloudcompare")
        out[name] = {
            "ours_median_s": _get(row, "ours", "median_s"),
            "cloudcompare_median_s": cc.get("median_s") if isinstance(cc, dict) else cc,
            "ratio_cloudcompare_over_ours": row.get("ratio_cloudcompare_over_ours"),
            "agree_within_1e-6_m": row.get("agree_within_1e-6_m"),
        }
    stage = d.get("compare_stage") or {}
    out["compare_stage"] = {k: stage.get(k) for k in ("median_s", "target_s", "verdict")}
    return out


def _colmap(d: dict[str, Any]) -> dict[str, Any]:
    cli = d.get("colmap_cli")
    return {
        "ours_total_s": _get(d, "ours", "total_s"),
        "colmap_cli_total_s": cli.get("total_s") if isinstance(cli, dict) else cli,
        "ratio_cli_over_ours": d.get("ratio_cli_over_ours"),
    }


def _console(d: dict[str, Any]) -> dict[str, Any]:
    keys = ("snapshot_points", "decimated_median_ms", "full_median_ms", "within_target")
    return {**{k: d.get(k) for k in keys}, "script_gzip_kb": _get(d, "script", "gzip_kb")}


def _capture(d: dict[str, Any]) -> dict[str, Any]:
    runs = d.get("runs", {})
    target = runs.get("target_100_12MP", {})
    service = runs.get("service_100_12MP", {})
    return {
        "growth": d.get("growth"),
        "target_100_12MP_s": target.get("reconstruct_s"),
        "target_median_m": target.get("distance_median_m"),
        "target_completeness_1cm": target.get("completeness_1cm"),
        "upload_to_cloud_100_12MP_s": service.get("upload_to_cloud_s"),
        "upload_to_cloud_peak_rss_mib": service.get("peak_rss_mib"),
    }


def _workers(d: dict[str, Any]) -> dict[str, Any]:
    keys = ("median_drain_wall_s", "median_jobs_per_min", "throughput_ratio_2_to_1", "runs")
    return {**{k: d.get(k) for k in keys}, "meets_target": d.get("meets_target")}


def _seed_args(seed: int) -> tuple[str, ...]:
    where = f"{TMP}/reconstruct_seed{seed}"
    return ("--seed", str(seed), "--scene", f"{where}/scene", "--work", f"{where}/work")


BENCHES: tuple[Bench, ...] = (
    Bench("poll", "bench.poll_bench", "poll.json", (), ("--seconds", "5"), ("wrk",), 1800, _poll),
    Bench(
        "upload", "bench.upload_bench", "upload.json", (), ("--size-mb", "200"), (), 1800, _upload
    ),
    Bench(
        "reconstruct",
        "bench.reconstruct_bench",
        "reconstruct.json",
        ("--scene", f"{TMP}/reconstruct/scene", "--work", f"{TMP}/reconstruct/work"),
        (
            "--scene",
            f"{TMP}/reconstruct/scene",
            "--work",
            f"{TMP}/reconstruct/work",
            "--preset",
            "fast",
        ),
        headline=_reconstruct,
    ),
    # the same cases on other generated scenes (the camera path and the objects follow the
    # seed): how far the bench scene's figures carry
    *(
        Bench(
            f"reconstruct_seed{seed}",
            "bench.reconstruct_bench",
            f"reconstruct_seed{seed}.json",
            (*_seed_args(seed), "--preset", "default"),
            (*_seed_args(seed), "--preset", "fast"),
            headline=_reconstruct,
        )
        for seed in (7, 3)
    ),
    Bench(
        "pose",
        "bench.pose_bench",
        "pose.json",
        ("--work", f"{TMP}/pose"),
        ("--work", f"{TMP}/pose", "--trials", "2", "--real-trials", "1"),
        headline=_pose,
    ),
    Bench(
        "scenarios",
        "bench.scenarios_bench",
        "scenarios.json",
        (),
        ("--quick",),
        headline=_scenarios,
    ),
    # the split of bench/worlds.py: tune on the first, report the second (bench/README.md)
    *(
        Bench(
            f"scenarios_{name}",
            "bench.scenarios_bench",
            f"scenarios_{name}.json",
            ("--set", name, "--real-camera"),
            ("--set", name, "--quick"),
            headline=_world_set,
        )
        for name in ("tuning", "test")
    ),
    # the inventory of every snapshot (issue #19), on the same split: tune / report
    *(
        Bench(
            f"inventory_{name}",
            "bench.inventory_bench",
            f"inventory_{name}.json",
            ("--set", name),
            ("--set", name, "--quick"),
            headline=_inventory,
        )
        for name in ("tuning", "test")
    ),
    Bench("c2c", "bench.c2c_bench", "c2c.json", (), ("--quick",), headline=_c2c),
    Bench("colmap", "bench.colmap_bench", "reconstruct_colmap.json", headline=_colmap),
    # cost at real capture sizes (#22): 30-200 photos, 1-12 MP, policy, matching, target
    Bench(
        "capture",
        "bench.capture_bench",
        "capture.json",
        (),
        ("--quick",),
        timeout_s=6 * 3600,
        headline=_capture,
    ),
    # several worker hosts (#22): the same queue on 1 worker (core 0) and 2 (cores 0 and 1)
    Bench(
        "workers",
        "bench.workers_bench",
        "workers.json",
        (),
        ("--quick",),
        headline=_workers,
    ),
    # the operator console (#20): a 2 M-point snapshot opened in headless Chromium
    Bench(
        "console",
        "bench.console_bench",
        "console.json",
        (),
        ("--points", "500000", "--runs", "1"),
        timeout_s=1800,
        headline=_console,
    ),
)


def ensure_tools() -> dict[str, str | None]:
    """Install missing tools with apt-get when root; returns tool → path or None, and says
    clearly what is missing otherwise."""

    def find(tool: str) -> str | None:
        return next((p for n in TOOLS[tool][0] if (p := shutil.which(n))), None)

    missing = [t for t in TOOLS if find(t) is None]
    if missing and os.geteuid() == 0 and shutil.which("apt-get"):
        packages = [TOOLS[t][1] for t in missing]
        print(f"[bench] installing {' '.join(packages)} with apt-get", flush=True)
        env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
        subprocess.run(["apt-get", "update", "-qq"], env=env, check=False)
        subprocess.run(
            ["apt-get", "install", "-y", "-qq", "--no-install-recommends", *packages],
            env=env,
            check=False,
        )
    found = {t: find(t) for t in TOOLS}
    for tool, path in found.items():
        if path is None:
            print(
                f"[bench] {tool} is missing (install: sudo apt-get install {TOOLS[tool][1]}); "
                "the comparisons that need it are skipped and recorded as such",
                flush=True,
            )
    return found


def run_one(bench: Bench, quick: bool, tools: dict[str, str | None]) -> dict[str, Any]:
    missing = [t for t in bench.requires if tools.get(t) is None]
    if missing:
        return {"status": f"skipped: {', '.join(missing)} not installed"}
    LOGS.mkdir(parents=True, exist_ok=True)
    log = LOGS / f"{bench.name}.log"
    results = RESULTS / "quick" if quick else RESULTS
    result_path = results / bench.result
    cmd = [sys.executable, "-m", bench.module, *(bench.quick_args if quick else bench.args)]
    cmd += ["--out", str(result_path)]
    print(f"[bench] {bench.name}: {' '.join(cmd[1:])}  (log: {log})", flush=True)
    before = result_path.stat().st_mtime if result_path.exists() else None
    t0 = time.perf_counter()
    try:
        with log.open("w") as fh:
            proc = subprocess.run(
                cmd, cwd=ROOT, stdout=fh, stderr=subprocess.STDOUT, timeout=bench.timeout_s
            )
        code: int | None = proc.returncode
    except subprocess.TimeoutExpired:
        code = None
    wall = round(time.perf_counter() - t0, 1)
    row: dict[str, Any] = {
        "command": " ".join(cmd[1:]),
        "exit_status": code,
        "wall_s": wall,
        "status": "ok" if code == 0 else ("timeout" if code is None else "failed"),
        "result_file": str(result_path.relative_to(ROOT)),
        "log": str(log),
    }
    fresh = result_path.exists() and result_path.stat().st_mtime != before
    if not fresh:
        row["result_file"] = None
        row["log_tail"] = log.read_text(errors="replace")[-1500:]
    else:
        try:
            row["headline"] = bench.headline(json.loads(result_path.read_text()))
        except Exception as exc:  # a changed result layout must not lose the summary
            row["headline"] = f"could not read headline figures: {exc}"
        if bench.name == "c2c" and tools.get("cloudcompare") is None:
            row["cloudcompare"] = "skipped: CloudCompare not installed"
        if bench.name == "colmap" and tools.get("colmap") is None:
            row["colmap_cli"] = "skipped: colmap not installed"
    print(f"[bench] {bench.name}: {row['status']} in {wall} s", flush=True)
    return row


def collect(results: Path, only: list[str]) -> int:
    """summary.json from existing result files (their own timestamps, no exit statuses)."""
    summary: dict[str, Any] = {"collected_from_existing_files": True, "benchmarks": {}}
    for bench in BENCHES:
        path = results / bench.result
        if (only and bench.name not in only) or not path.exists():
            continue
        row: dict[str, Any] = {
            "status": "collected",
            "result_file": str(path.relative_to(ROOT)),
            "modified": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(path.stat().st_mtime)),
        }
        try:
            row["headline"] = bench.headline(json.loads(path.read_text()))
        except Exception as exc:
            row["headline"] = f"could not read headline figures: {exc}"
        summary["benchmarks"][bench.name] = row
    (results / "summary.json").write_text(json.dumps(summary, indent=1, default=str))
    print(json.dumps(summary, indent=1, default=str))
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="make bench", description=__doc__.splitlines()[0])
    names = [b.name for b in BENCHES]
    parser.add_argument("--only", default="", help=f"comma-separated subset of {names}")
    parser.add_argument("--quick", action="store_true", help="smoke run: fewer scenarios/views")
    parser.add_argument(
        "--collect",
        action="store_true",
        help="run nothing: rebuild summary.json from the result files already there",
    )
    args = parser.parse_args(argv)
    only = [n for n in args.only.split(",") if n]
    unknown = set(only) - set(names)
    if unknown:
        parser.error(f"unknown benchmark(s) {sorted(unknown)}; choose from {names}")
    if args.collect:
        return collect(RESULTS / "quick" if args.quick else RESULTS, only)
    tools = ensure_tools()
    results = RESULTS / "quick" if args.quick else RESULTS
    results.mkdir(parents=True, exist_ok=True)
    summary_path = results / "summary.json"
    summary: dict[str, Any] = {
        "quick": args.quick,
        "cpus": os.cpu_count(),
        "load_average_at_start": os.getloadavg(),
        "tools": tools,
        "benchmarks": {},
    }
    if only and summary_path.exists():  # a partial run keeps the other benchmarks' rows
        with contextlib.suppress(ValueError):
            summary["benchmarks"] = json.loads(summary_path.read_text()).get("benchmarks", {})
    t0 = time.perf_counter()
    for bench in BENCHES:
        if only and bench.name not in only:
            continue
        summary["benchmarks"][bench.name] = run_one(bench, args.quick, tools)
        summary_path.write_text(json.dumps(summary, indent=1, default=str))
    summary["wall_s"] = round(time.perf_counter() - t0, 1)
    summary["load_average_at_end"] = os.getloadavg()
    summary_path.write_text(json.dumps(summary, indent=1, default=str))
    ran = [summary["benchmarks"][b.name] for b in BENCHES if not only or b.name in only]
    print(json.dumps({b: r.get("status") for b, r in summary["benchmarks"].items()}, indent=1))
    return 0 if all(r["status"] == "ok" or r["status"].startswith("skipped") for r in ran) else 1


if __name__ == "__main__":
    raise SystemExit(main())
