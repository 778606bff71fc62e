"""``make demo``: the whole service on a generated before/after scene.

Generates a scene with built-in shapes (no data files), starts the embedded service, creates
the object library and the environment, uploads both captures over HTTP as a capture station
would, polls with progress, prints the changes found next to the ground truth with their pose
errors, and writes an HTML report. Exits non-zero if anything fails or a change is missed.
"""

from __future__ import annotations

import argparse
import shutil
import signal
import socket
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx

from app.client import Client, check, embedded_service, poll_job, read_json
from workers.demo.evaluate import Match, match_changes
from workers.demo.report import write_report
from workers.pipeline.synth import generate, preset

ADMIN_KEY = "td_demo_admin_key_0123456789abcdef"


def _matrix(pose: Any) -> str:
    if pose is None:
        return "    (none)"
    return "\n".join("    [" + "  ".join(f"{v:8.4f}" for v in row) + "]" for row in pose)


def _object_library(client: httpx.Client, scene_dir: Path, classes: list[str]) -> None:
    """Upload every class's model (``objects/<name>.ply``) and wait for each to be prepared."""
    jobs = []
    for name in classes:
        with (scene_dir / "objects" / f"{name}.ply").open("rb") as fh:
            obj = check(
                client.post(
                    "/v1/objects", files={"file": (f"{name}.ply", fh)}, data={"name": name}
                ),
                202,
            )
        jobs.append((name, obj["job"]["id"]))
    for name, job_id in jobs:
        job = poll_job(client, job_id, f"object {name}")
        if job["state"] != "succeeded":
            raise SystemExit(f"object {name} failed: {job.get('error')}")


def _snapshot(client: httpx.Client, env_id: str, scene_dir: Path, capture: str) -> dict[str, Any]:
    """Upload one capture folder as a capture station does (packed into one tar, a
    resumable upload with a content-derived Idempotency-Key: :class:`Client`), wait for its
    reconstruction, print its quality line and return the snapshot."""
    with Client(str(client.base_url), ADMIN_KEY) as station:
        uploaded = station.upload_capture(env_id, scene_dir / capture)
    job = poll_job(client, uploaded.job, f"reconstruct {capture}")
    if job["state"] != "succeeded":
        raise SystemExit(f"reconstruction of '{capture}' failed: {job.get('error')}")
    snap = check(client.get(f"/v1/snapshots/{uploaded.snapshot}"), 200)
    q = snap["quality"]
    residual = q.get("alignment_residual_m")
    aligned = (
        "first snapshot: nothing to align to"
        if residual is None
        else f"alignment residual {1000 * residual:.1f} mm"
    )
    print(
        f"     {q.get('images_registered')}/{q.get('images_total')} images, "
        f"{q.get('points')} points, "
        f"reprojection {q.get('mean_reprojection_error_px') or 0:.2f} px, "
        f"marker residual {1000 * (q.get('marker_residual_m') or 0):.1f} mm, {aligned}"
    )
    return snap


def _comparison(client: httpx.Client, comparison_id: str | None) -> dict[str, Any]:
    """Wait for the automatic comparison (compare + pose) and return it."""
    if comparison_id is None:
        raise SystemExit("no automatic comparison was started")
    comparison = check(client.get(f"/v1/comparisons/{comparison_id}"), 200)
    job = poll_job(client, comparison["job"], "compare + pose")
    if job["state"] != "succeeded":
        raise SystemExit(f"comparison failed: {job.get('error')}")
    return check(client.get(f"/v1/comparisons/{comparison_id}"), 200)


@dataclass(frozen=True)
class _Run:
    """What the service answered: the environment, the finished comparison and its twin
    state."""

    environment_id: str
    comparison: dict[str, Any]
    state: dict[str, Any]


def _run_service(
    client: httpx.Client,
    scene_dir: Path,
    scenario: str,
    classes: list[str],
    timings: dict[str, float],
) -> _Run:
    """Steps 3-4 against the running service; ``timings`` gets one entry per step (s)."""
    t = time.monotonic()
    print("3. creating the object library")
    _object_library(client, scene_dir, classes)
    timings["object library"] = time.monotonic() - t

    env = check(
        client.post(
            "/v1/environments",
            json={
                "name": f"demo-{scenario}",
                "classes": classes,
                "reference": read_json(scene_dir / "reference.json"),
            },
        ),
        201,
    )
    print(f"4. environment {env['id']} with classes {classes}")

    snaps = []
    for capture in ("before", "after"):
        t = time.monotonic()
        snaps.append(_snapshot(client, env["id"], scene_dir, capture))
        timings[f"reconstruct {capture}"] = time.monotonic() - t

    t = time.monotonic()
    comparison = _comparison(client, snaps[1]["comparison"])
    timings["compare + pose"] = time.monotonic() - t
    state = check(client.get(f"/v1/environments/{env['id']}/state"), 200)
    return _Run(env["id"], comparison, state)


def console_url(base_url: str, environment_id: str) -> str:
    """The operator console's page of an environment (served by the API at /ui/)."""
    return f"{base_url.rstrip('/')}/ui/#/environments/{environment_id}"


def _console_keys(client: httpx.Client) -> str:
    """A read-only key for looking without acting (the admin key may upload and re-run)."""
    created = check(client.post("/v1/keys", json={"name": "demo viewer", "scopes": ["read"]}), 201)
    return str(created["key"])


def _print_console(url: str, read_key: str, keep: bool, out: Path) -> None:
    print(f"\nconsole: {url}")
    print(f"   sign in with the admin key {ADMIN_KEY}")
    print(f"   or the read-only key       {read_key}")
    if keep:
        print("   the service keeps running (KEEP=1): open the URL, press Ctrl-C to stop it")
    else:
        print(
            "   the service has stopped; to open the console run `make demo KEEP=1`, or serve "
            f"this demo's data again: TWINDELTA_DATA_DIR={out / 'data'} make serve "
            "(then the same page on port 8000)"
        )


def _port_free(port: int) -> bool:
    """Whether nothing listens on 127.0.0.1:``port`` (a service already there would answer
    the demo's requests instead of its own)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def _wait_for_interrupt() -> None:
    """Sleep until Ctrl-C (SIGINT) or SIGTERM; the caller then stops the service."""

    def stop(_signum: int, _frame: Any) -> None:
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)  # also when started in the background (inherited ignore)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        print("\nstopping the service")


def _print_changes(matches: list[Match], extra: list[dict[str, Any]]) -> None:
    """Step 5: each true change next to the one found, with pose errors and both poses."""
    print("\n5. changes found (ground truth on the right)")
    print(
        f"   {'type':<9} {'object':<14} {'metric':>6}  {'truth':<22} "
        f"{'Δt mm':>7} {'ΔR °':>6}  verified"
    )
    for m in matches:
        f = m.found or {}
        ident = f.get("identification") or {}
        quality = f.get("pose_quality") or {}
        dt = (
            f"{m.translation_error_m * 1000:7.1f}"
            if m.translation_error_m is not None
            else "      -"
        )
        dr = f"{m.rotation_error_deg:6.2f}" if m.rotation_error_deg is not None else "     -"
        metric = ident.get("metric", 0)
        found = f"{f.get('type', 'MISSED'):<9} {f.get('object', '')!s:<14} {metric:6.2f}"
        print(
            f"   {found}  {m.truth['type'] + ' ' + m.truth['object']:<22} {dt} {dr}  "
            f"{quality.get('verified', '-')}"
        )
        if f.get("pose") is not None:
            print("   env_from_object (found):")
            print(_matrix(f["pose"]))
            print("   env_from_object (true):")
            print(_matrix(m.truth["pose"]))
    for e in extra:
        print(f"   FALSE CHANGE: {e['type']} {e.get('object')}")


def _verdict(matches: list[Match], extra: list[dict[str, Any]]) -> int:
    """0 when every change was found with a pose within 2 cm and 5°, and nothing false."""
    missed = [m for m in matches if m.found is None]
    wrong_pose = [
        m
        for m in matches
        if m.translation_error_m is not None
        and (m.translation_error_m > 0.02 or (m.rotation_error_deg or 0) > 5)
    ]
    if missed or extra or wrong_pose:
        print(f"FAILED: {len(missed)} missed, {len(extra)} false, {len(wrong_pose)} poses off")
        return 1
    print("OK: every change found with the right type and object")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="make demo", description=__doc__)
    parser.add_argument("--scenario", default="multiple")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--preset", default="demo")
    parser.add_argument("--out", type=Path, default=Path("demo-output"))
    parser.add_argument(
        "--keep",
        action="store_true",
        help="keep the service running at the end (open the console) until Ctrl-C",
    )
    parser.add_argument("--port", type=int, default=None, help="default: a free port")
    args = parser.parse_args(argv)
    if args.port is not None and not _port_free(args.port):
        raise SystemExit(
            f"port {args.port} is in use: stop what listens there or give another "
            "(make demo KEEP=1 PORT=8001)"
        )
    out: Path = args.out.resolve()
    shutil.rmtree(out, ignore_errors=True)
    timings: dict[str, float] = {}
    t0 = time.monotonic()

    print(f"1. generating the '{args.scenario}' scene (seed {args.seed}) under {out}/scene")
    scene_dir = out / "scene"
    generate(scene_dir, args.scenario, args.seed, preset(args.preset))
    truth = read_json(scene_dir / "ground_truth.json")
    classes: list[str] = truth["classes"]
    timings["generate scene"] = time.monotonic() - t0

    print("2. starting the embedded service (SQLite, file-system broker, local storage)")
    with embedded_service(out / "data", ADMIN_KEY, out / "service.log", port=args.port) as client:
        run = _run_service(client, scene_dir, args.scenario, classes, timings)
        matches, extra = match_changes(truth, run.comparison["changes"])
        _print_changes(matches, extra)
        print(f"\n   twin state: {len(run.state['objects'])} instance(s)")
        timings["total"] = time.monotonic() - t0
        url = console_url(str(client.base_url), run.environment_id)
        report = write_report(
            out / "report", scene_dir, run.comparison, matches, extra, classes, timings, url
        )
        print(f"\nreport: {report}")
        print("timings: " + ", ".join(f"{k} {v:.0f} s" for k, v in timings.items()))
        verdict = _verdict(matches, extra)
        _print_console(url, _console_keys(client), args.keep, out)
        if args.keep:
            _wait_for_interrupt()
    return verdict
