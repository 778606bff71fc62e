"""``twindelta`` command line: ``serve`` (the embedded service: API + workers, no external
servers), ``migrate``, ``create-key``, ``reencrypt-secrets``, ``openapi``.

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
from pathlib import Path

from alembic import command
from alembic.config import Config

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
    args = parser.parse_args(argv)
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
