"""Job-status polling under load: 50 concurrent clients (wrk) against GET /v1/jobs/{id},
on the embedded setup (SQLite) and on PostgreSQL. The same run measures GET /healthz (no
database, no auth) as the framework's own ceiling on this machine, so the figures can be
read as ratios on a noisy shared machine. Targets: ≥ 1,000 polls/s and p99 ≤ 30 ms."""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx

from app.client import REPO_ROOT, check, free_port

KEY = "td_bench_admin_key_0123456789abcdef"
PG_ADMIN = "postgresql+psycopg://postgres@127.0.0.1:5432/postgres"


def _seconds(value: str) -> float:
    number, unit = re.fullmatch(r"([\d.]+)(us|ms|s|m)", value).groups()  # type: ignore[union-attr]
    return float(number) * {"us": 1e-6, "ms": 1e-3, "s": 1.0, "m": 60.0}[unit]


def wrk(url: str, seconds: int, connections: int, threads: int = 2) -> dict[str, float]:
    """Run wrk with the bearer header; requests/s and latency percentiles in ms."""
    script = Path(tempfile.mkstemp(suffix=".lua")[1])
    script.write_text(f'wrk.headers["Authorization"] = "Bearer {KEY}"\n')
    out = subprocess.run(
        [
            "wrk",
            f"-t{threads}",
            f"-c{connections}",
            f"-d{seconds}s",
            "--latency",
            "-s",
            str(script),
            url,
        ],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    script.unlink()
    rps = float(re.search(r"Requests/sec:\s+([\d.]+)", out).group(1))  # type: ignore[union-attr]
    lat = {p: _seconds(v) * 1000 for p, v in re.findall(r"\s+(50|75|90|99)%\s+(\S+)", out)}
    errors = re.search(r"Non-2xx or 3xx responses: (\d+)", out)
    return {
        "requests_per_s": rps,
        "p50_ms": lat["50"],
        "p90_ms": lat["90"],
        "p99_ms": lat["99"],
        "non_2xx": float(errors.group(1)) if errors else 0.0,
    }


def run_mode(mode: str, seconds: int, api_workers: int) -> dict[str, Any]:
    data = Path(tempfile.mkdtemp(prefix=f"poll-{mode}-"))
    env = {k: v for k, v in os.environ.items() if not k.startswith("TWINDELTA_")}
    env.update(TWINDELTA_DATA_DIR=str(data), TWINDELTA_BOOTSTRAP_ADMIN_KEY=KEY)
    db_name = None
    if mode == "postgres":
        from sqlalchemy import create_engine, text

        db_name = f"twindelta_bench_{os.getpid()}"
        admin = create_engine(PG_ADMIN, isolation_level="AUTOCOMMIT")
        with admin.connect() as conn:
            conn.execute(text(f'DROP DATABASE IF EXISTS "{db_name}" WITH (FORCE)'))
            conn.execute(text(f'CREATE DATABASE "{db_name}"'))
        admin.dispose()
        env["TWINDELTA_DATABASE_URL"] = PG_ADMIN.rsplit("/", 1)[0] + f"/{db_name}"
    subprocess.run([sys.executable, "-m", "app.cli", "migrate"], env=env, cwd=REPO_ROOT, check=True)
    port = free_port()
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "uvicorn",
            "app.main:create_app",
            "--factory",
            "--port",
            str(port),
            "--log-level",
            "warning",
            "--workers",
            str(api_workers),
        ],
        env=env,
        cwd=REPO_ROOT,
        start_new_session=True,
    )
    try:
        client = httpx.Client(
            base_url=f"http://127.0.0.1:{port}", headers={"Authorization": f"Bearer {KEY}"}
        )
        for _ in range(200):
            try:
                if client.get("/readyz").status_code == 200:
                    break
            except httpx.TransportError:
                time.sleep(0.2)
        env_id = check(
            client.post("/v1/environments", json={"name": "poll", "classes": ["a"]}), 201
        )["id"]
        box = (
            "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
            "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
            "end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n"
        )
        job = check(
            client.post("/v1/objects", files={"file": ("a.ply", box.encode())}, data={"name": "a"}),
            202,
        )["job"]["id"]
        del env_id
        base = f"http://127.0.0.1:{port}"
        wrk(f"{base}/v1/jobs/{job}", 2, 50)  # warm-up
        return {
            "mode": mode,
            "api_workers": api_workers,
            "healthz_baseline": wrk(f"{base}/healthz", seconds, 50),
            "job_poll": wrk(f"{base}/v1/jobs/{job}", seconds, 50),
        }
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(timeout=30)
        shutil.rmtree(data, ignore_errors=True)
        if db_name:
            from sqlalchemy import create_engine, text

            admin = create_engine(PG_ADMIN, isolation_level="AUTOCOMMIT")
            with admin.connect() as conn:
                conn.execute(text(f'DROP DATABASE IF EXISTS "{db_name}" WITH (FORCE)'))
            admin.dispose()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seconds", type=int, default=15)
    parser.add_argument("--api-workers", type=int, default=2)
    parser.add_argument("--out", type=Path, default=REPO_ROOT / "bench" / "results" / "poll.json")
    args = parser.parse_args(argv)
    if shutil.which("wrk") is None:
        print("wrk is not installed: make bench installs it (apt-get install wrk)")
        return 1
    results = [run_mode(m, args.seconds, args.api_workers) for m in ("embedded", "postgres")]
    for r in results:
        r["ratio_to_healthz"] = (
            r["job_poll"]["requests_per_s"] / r["healthz_baseline"]["requests_per_s"]
        )
        r["meets_target"] = (
            r["job_poll"]["requests_per_s"] >= 1000 and r["job_poll"]["p99_ms"] <= 30
        )
    report = {
        "clients": 50,
        "seconds": args.seconds,
        "nproc": os.cpu_count(),
        "load_avg_at_end": os.getloadavg(),
        "targets": {"polls_per_s": 1000, "p99_ms": 30},
        "results": results,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=1))
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
