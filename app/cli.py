"""``twindelta`` command line: ``serve`` (the embedded service: API + workers, no external
servers), ``migrate``, ``create-key``, ``reencrypt-secrets``, ``openapi``; and a capture
station's commands over HTTP (:class:`app.client.Client`): ``upload DIR --env NAME [--wait]``
(resumable, with progress bars and a content-derived Idempotency-Key), ``changes``, ``state``.

``serve`` starts the same processes production runs (uvicorn, a Celery worker for the cpu
queue, one for the webhooks queue, one for the maintenance queue with the beat schedule), as
child processes; it never imports the workers itself.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, TextIO

from alembic import command
from alembic.config import Config

from app.client import ApiError, Client
from app.core.settings import get_settings

REPO_ROOT = Path(__file__).resolve().parents[1]
MAX_RESTARTS = 5
RESTART_WINDOW_S = 300.0


def migrate() -> None:
    """Bring the configured database to the newest schema (``alembic upgrade head``)."""
    settings = get_settings()
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    config = Config(str(REPO_ROOT / "alembic.ini"))
    config.attributes["url"] = settings.resolved_database_url
    command.upgrade(config, "head")


def worker_commands(data_dir: Path, cpu_concurrency: int) -> list[list[str]]:
    """The Celery worker command lines of the embedded service: the cpu queue (processes);
    webhook deliveries on a thread pool of their own; and the maintenance queue (webhook
    dispatch, job sweeper, retention) with the beat schedule, in a separate process, so
    deliveries that hang until their deadline can never hold up the periodic tasks."""
    celery = [sys.executable, "-m", "celery", "-A", "workers.celery_app"]
    return [
        [
            *celery,
            "worker",
            "-Q",
            "cpu",
            "-c",
            str(cpu_concurrency),
            "-n",
            "cpu@%h",
            "--loglevel",
            "INFO",
            "--max-tasks-per-child",
            "20",
        ],
        [
            *celery,
            "worker",
            "-Q",
            "webhooks",
            "-P",
            "threads",
            "-c",
            "4",
            "-n",
            "webhooks@%h",
            "--loglevel",
            "INFO",
        ],
        [
            *celery,
            "worker",
            "-Q",
            "maintenance",
            "-P",
            "threads",
            "-c",
            "4",
            "-n",
            "maintenance@%h",
            "--loglevel",
            "INFO",
            "-B",
            "-s",
            str(data_dir / "celerybeat-schedule"),
        ],
    ]


def serve(host: str, port: int, cpu_concurrency: int) -> int:
    """Run API and workers until one exits or a signal arrives; returns an exit status."""
    settings = get_settings()
    migrate()
    data_dir = settings.data_dir.resolve()
    env = {**os.environ, "TWINDELTA_DATA_DIR": str(data_dir)}
    api = [
        sys.executable,
        "-m",
        "uvicorn",
        "app.main:create_app",
        "--factory",
        "--host",
        host,
        "--port",
        str(port),
        "--log-level",
        "info",
    ]
    commands = [api, *worker_commands(data_dir, cpu_concurrency)]
    procs = [subprocess.Popen(cmd, env=env, cwd=REPO_ROOT) for cmd in commands]
    restarts: list[list[float]] = [[] for _ in commands]
    print(f"twindelta: serving on http://{host}:{port} (data in {data_dir})", flush=True)
    stopping = False

    def stop(_signum: int, _frame: object) -> None:
        nonlocal stopping
        stopping = True

    signal.signal(signal.SIGINT, stop)
    signal.signal(signal.SIGTERM, stop)
    status = 0
    while not stopping:
        for i, (cmd, proc) in enumerate(zip(commands, procs, strict=True)):
            code = proc.poll()
            if code is None:
                continue
            name = " ".join(cmd[2:5])
            now = time.monotonic()
            recent = [t for t in restarts[i] if now - t < RESTART_WINDOW_S]
            if i == 0 or len(recent) >= MAX_RESTARTS:
                # The API, or a worker that keeps dying: stop everything and say so.
                print(f"twindelta: {name} exited with {code}; stopping", file=sys.stderr)
                stopping, status = True, code or 1
                break
            # A crashed worker is restarted; its jobs are recovered by the sweeper.
            print(f"twindelta: {name} exited with {code}; restarting it", file=sys.stderr)
            restarts[i] = [*recent, now]
            procs[i] = subprocess.Popen(cmd, env=env, cwd=REPO_ROOT)
        time.sleep(0.5)
    for proc in procs:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + 20
    for proc in procs:
        try:
            proc.wait(timeout=max(deadline - time.monotonic(), 0.1))
        except subprocess.TimeoutExpired:
            proc.kill()
    return status


def create_key(name: str, scopes: list[str], environment_ids: list[str] | None = None) -> str:
    from app.core import auth
    from app.core.db import transaction

    with transaction() as session:
        _row, token = auth.create_key(session, name, scopes, environment_ids=environment_ids)
    return token


def reencrypt_secrets() -> int:
    """Re-encrypt the stored webhook secrets under the first key of TWINDELTA_SECRET_KEY."""
    from app.core import webhooks
    from app.core.db import transaction

    with transaction() as session:
        return webhooks.reencrypt_secrets(session, get_settings())


# --- the capture station's commands (over HTTP, app/client.py) ---------------------------


class ProgressBar:
    """One line on ``stream`` redrawn in place: ``label [#####.....] 45.0% note``."""

    def __init__(self, stream: TextIO, width: int = 30) -> None:
        self.stream, self.width, self.last = stream, width, ""

    def draw(self, label: str, fraction: float, note: str = "") -> None:
        fraction = min(max(fraction, 0.0), 1.0)
        bar = "#" * int(fraction * self.width)
        line = f"{label:<8} [{bar:<{self.width}}] {fraction * 100:5.1f}%  {note}"
        if line != self.last:
            self.stream.write("\r" + line.ljust(90))
            self.stream.flush()
            self.last = line

    def done(self) -> None:
        if self.last:
            self.stream.write("\n")
            self.stream.flush()
        self.last = ""


def _bytes_reporter(bar: ProgressBar) -> Callable[[int, int], None]:
    started = time.monotonic()

    def report(offset: int, size: int) -> None:
        rate = offset / 1e6 / max(time.monotonic() - started, 1e-3)
        note = f"{offset / 1e6:.1f}/{size / 1e6:.1f} MB  {rate:.1f} MB/s"
        bar.draw("upload", offset / size if size else 1.0, note)

    return report


def _job_reporter(bar: ProgressBar, label: str) -> Callable[[dict[str, Any]], None]:
    def report(job: dict[str, Any]) -> None:
        bar.draw(
            label, float(job.get("progress") or 0.0), f"{job['state']} {job.get('stage') or ''}"
        )

    return report


def _changes_table(comparison: dict[str, Any]) -> str:
    rows = [f"comparison {comparison['id']} ({comparison['state']})"]
    rows.append(f"{'type':<12} {'object':<20} {'x m':>8} {'y m':>8} {'z m':>8}  verified  instance")
    for change in comparison.get("changes", []):
        pose = change.get("pose") or change.get("previous_pose")
        xyz = [f"{pose[i][3]:8.3f}" for i in range(3)] if pose else ["       -"] * 3
        verified = (change.get("pose_quality") or {}).get("verified")
        shown = "-" if verified is None else str(verified)
        rows.append(
            f"{change['type']:<12} {change.get('object') or '-':<20} {' '.join(xyz)}  "
            f"{shown:<8}  {change.get('instance_id') or '-'}"
        )
    if not comparison.get("changes"):
        rows.append("(no changes)")
    return "\n".join(rows)


def _state_table(state: dict[str, Any]) -> str:
    twin = state.get("twin") or {}
    rows = [
        f"twin at snapshot {twin.get('snapshot')} (seq {twin.get('seq')}, {twin.get('status')})"
    ]
    rows.append(
        f"{'object':<20} {'x m':>8} {'y m':>8} {'z m':>8}  since snapshot  instance  external id"
    )
    for obj in state.get("objects", []):
        pose = obj.get("pose")
        xyz = [f"{pose[i][3]:8.3f}" for i in range(3)] if pose else ["       -"] * 3
        since = obj.get("since_snapshot") or "-"  # none: seeded before any snapshot
        rows.append(
            f"{obj['object']:<20} {' '.join(xyz)}  {since:<14}  "
            f"{obj['instance_id']}  {obj.get('external_id') or '-'}"
        )
    if not state.get("objects"):
        rows.append("(no objects)")
    return "\n".join(rows)


def _client(args: argparse.Namespace) -> Client:
    if not args.key:
        raise ApiError(401, "Unauthorized", "give --key or set TWINDELTA_API_KEY", "twindelta")
    return Client(args.url, args.key, retries=args.retries)


def upload_command(args: argparse.Namespace) -> int:
    """``twindelta upload DIR --env NAME [--wait]``: pack, upload resumably, and with
    ``--wait`` follow the job's stages and print the changes; 1 on any failure."""
    if not args.dir.is_dir():
        print(f"twindelta upload: {args.dir}: no such folder", file=sys.stderr)
        return 1
    bar = ProgressBar(sys.stderr)
    with _client(args) as client:
        env = client.environment(args.env)
        result = client.upload_capture(
            env["id"],
            args.dir,
            chunk_bytes=args.chunk_mb * 1024**2,
            on_bytes=None if args.quiet else _bytes_reporter(bar),
        )
        bar.done()
        print(f"snapshot {result.snapshot}  job {result.job}")
        if not args.wait:
            return 0
        job = client.wait_job(
            result.job,
            on_job=None if args.quiet else _job_reporter(bar, "job"),
            timeout_s=args.timeout,
        )
        bar.done()
        if job["state"] != "succeeded":
            error = job.get("error") or {}
            print(
                f"twindelta: job {job['id']} {job['state']}: {error.get('code', '')} "
                f"{error.get('detail', '')}",
                file=sys.stderr,
            )
            return 1
        comparison = client.outcome(result.snapshot, timeout_s=args.timeout)
    if comparison is None:
        print("no comparison: the first snapshot of the environment (the twin starts here)")
        return 0
    print(json.dumps(comparison, indent=2) if args.json else _changes_table(comparison))
    return 0 if comparison["state"] == "succeeded" else 1


def changes_command(args: argparse.Namespace) -> int:
    """``twindelta changes --env NAME``: the newest comparison's changes."""
    with _client(args) as client:
        env = client.environment(args.env)
        found = client.comparisons(env["id"])
    if not found:
        print(f"environment {env['name']}: no comparisons yet")
        return 0
    print(json.dumps(found[0], indent=2) if args.json else _changes_table(found[0]))
    return 0


def state_command(args: argparse.Namespace) -> int:
    """``twindelta state --env NAME``: the twin's objects and poses."""
    with _client(args) as client:
        state = client.state(client.environment(args.env)["id"])
    print(json.dumps(state, indent=2) if args.json else _state_table(state))
    return 0


def seed_command(args: argparse.Namespace) -> int:
    """``twindelta seed FILE --env NAME``: import the twin platform's objects (a ``.csv``,
    else a JSON list; README "Seeding the twin"), all or nothing; prints what was made."""
    kind = "text/csv" if args.file.suffix.lower() == ".csv" else "application/json"
    body = args.file.read_bytes()
    with _client(args) as client:
        made = client.import_objects(client.environment(args.env)["id"], body, kind)
    if args.json:
        print(json.dumps(made, indent=2))
        return 0
    print(f"seeded {len(made)} instance(s)")
    for obj in made:
        print(f"{obj['object']:<20} {obj['instance_id']}  {obj.get('external_id') or '-'}")
    return 0


def _station_parsers(sub: Any) -> None:
    """``upload``, ``changes``, ``state``, ``seed``: the commands over HTTP."""
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--env", required=True, help="environment name or id")
    common.add_argument("--url", default=os.environ.get("TWINDELTA_URL", "http://127.0.0.1:8000"))
    common.add_argument(
        "--key", default=os.environ.get("TWINDELTA_API_KEY"), help="default: $TWINDELTA_API_KEY"
    )
    common.add_argument("--json", action="store_true", help="print JSON instead of a table")
    common.add_argument("--retries", type=int, default=8, help="per request, with backoff")
    p_up = sub.add_parser(
        "upload", parents=[common], help="upload a capture folder resumably (tus)"
    )
    p_up.add_argument("dir", type=Path, help="images, YOLO labels, optional cameras.json")
    p_up.add_argument("--wait", action="store_true", help="follow the job, print the changes")
    p_up.add_argument("--chunk-mb", type=int, default=64, help="bytes per PATCH, MiB")
    p_up.add_argument("--timeout", type=float, default=3600.0, help="--wait's limit, s")
    p_up.add_argument("--quiet", action="store_true", help="no progress bars")
    sub.add_parser("changes", parents=[common], help="the newest comparison's changes")
    sub.add_parser("state", parents=[common], help="the twin's objects and their poses")
    p_seed = sub.add_parser(
        "seed", parents=[common], help="seed the twin with the platform's objects (admin key)"
    )
    p_seed.add_argument("file", type=Path, help="a .csv (object, external_id, m00..m33) or JSON")


STATION_COMMANDS = {
    "upload": upload_command,
    "changes": changes_command,
    "state": state_command,
    "seed": seed_command,
}


def openapi_json() -> str:
    from app.main import create_app

    return json.dumps(create_app().openapi(), indent=2, sort_keys=True) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="twindelta")
    sub = parser.add_subparsers(dest="command", required=True)
    p_serve = sub.add_parser("serve", help="API and workers with no external servers")
    p_serve.add_argument("--host", default=os.environ.get("HOST", "127.0.0.1"))
    p_serve.add_argument("--port", type=int, default=int(os.environ.get("PORT", "8000")))
    p_serve.add_argument("--cpu-workers", type=int, default=1)
    sub.add_parser("migrate", help="alembic upgrade head on the configured database")
    p_key = sub.add_parser("create-key", help="create an API key and print it")
    p_key.add_argument("--name", default="cli")
    p_key.add_argument(
        "--scopes", default="admin", help="comma-separated: capture,read,metrics,admin"
    )
    p_key.add_argument(
        "--environments",
        help="comma-separated environment ids the key is limited to (default: every one)",
    )
    sub.add_parser(
        "reencrypt-secrets",
        help="re-encrypt stored secrets under the first key of TWINDELTA_SECRET_KEY",
    )
    p_api = sub.add_parser("openapi", help="print or write the OpenAPI document")
    p_api.add_argument("--out", type=Path)
    _station_parsers(sub)
    args = parser.parse_args(argv)
    if args.command in STATION_COMMANDS:
        try:
            return STATION_COMMANDS[args.command](args)
        except (ApiError, OSError, ValueError, TimeoutError) as exc:
            print(f"\ntwindelta {args.command}: {exc}", file=sys.stderr)
            return 1
    if args.command == "serve":
        return serve(args.host, args.port, args.cpu_workers)
    if args.command == "migrate":
        migrate()
        return 0
    if args.command == "reencrypt-secrets":
        print(f"re-encrypted {reencrypt_secrets()} webhook secrets")
        return 0
    if args.command == "create-key":
        envs = args.environments.split(",") if args.environments else None
        print(create_key(args.name, args.scopes.split(","), envs))
        return 0
    text = openapi_json()
    if args.out:
        args.out.write_text(text)
    else:
        sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
