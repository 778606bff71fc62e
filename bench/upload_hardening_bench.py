"""Hostile uploads against a real API process (uvicorn, embedded SQLite): what each costs the
server and how it is answered. A: 80 MiB multipart without a key (bytes spooled to the temp
folder, staging, RSS); B: an 80 MiB JSON body with a key (RSS); C: a ~155 kB zip bomb that
inflates to 151 MB (bytes staged); D: a tar.gz of 150,000 folder entries (RSS); E: a 16-bit
RGBA PNG of 7000×7000 (372 kB); F: the SQLite write lock - how long POST /v1/keys waits
while a 20 MB zip of 990 images and labels is checked.

    python -m bench.upload_hardening_bench [--tree DIR] [--out bench/results/uploads.json]

``--tree`` runs another checkout's code (e.g. a ``git worktree`` of an older commit) for a
before/after comparison."""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import shutil
import signal
import struct
import subprocess
import sys
import tarfile
import tempfile
import threading
import time
import zipfile
import zlib
from pathlib import Path

import httpx
import numpy as np
from PIL import Image

from app.client import REPO_ROOT, free_port

TREE = REPO_ROOT
ADMIN = "td_measure_admin_key_0123456789abcdef"
MB = 1024**2


def rss(pid: int) -> tuple[int, int]:
    status = Path(f"/proc/{pid}/status").read_text()
    vals = {}
    for line in status.splitlines():
        if line.startswith(("VmRSS", "VmHWM")):
            k, v = line.split(":")
            vals[k] = int(v.split()[0]) // 1024
    return vals["VmRSS"], vals["VmHWM"]


def reset_hwm(pid: int) -> None:
    with contextlib.suppress(OSError):  # resets VmHWM (Linux)
        Path(f"/proc/{pid}/clear_refs").write_text("5")


def tmp_free() -> int:
    st = os.statvfs(tempfile.gettempdir())
    return st.f_bavail * st.f_frsize


def tree_bytes(root: Path) -> int:
    total = 0
    if root.exists():
        for p in root.rglob("*"):
            try:
                if p.is_file():
                    total += p.stat().st_size
            except OSError:
                pass
    return total


class Watch:
    """Poll a value in a thread; keep its max (or min)."""

    def __init__(self, fn, mode="max"):
        self.fn, self.mode, self.best = fn, mode, None
        self.stop = False
        self.t = threading.Thread(target=self.run, daemon=True)
        self.t.start()

    def run(self):
        while not self.stop:
            v = self.fn()
            if self.best is None or (v > self.best if self.mode == "max" else v < self.best):
                self.best = v
            time.sleep(0.005)

    def done(self):
        self.stop = True
        self.t.join()
        return self.best


def main(argv: list[str] | None = None) -> int:
    global TREE
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tree", type=Path, default=REPO_ROOT)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    TREE = args.tree.resolve()
    data = Path(tempfile.mkdtemp(prefix="measure-"))
    env = {k: v for k, v in os.environ.items() if not k.startswith("TWINDELTA_")}
    env.update(
        TWINDELTA_DATA_DIR=str(data), TWINDELTA_BOOTSTRAP_ADMIN_KEY=ADMIN, PYTHONPATH=str(TREE)
    )
    subprocess.run([sys.executable, "-m", "app.cli", "migrate"], env=env, cwd=TREE, check=True)
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
        ],
        cwd=TREE,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    base = f"http://127.0.0.1:{port}"
    admin = {"Authorization": f"Bearer {ADMIN}"}
    for _ in range(200):
        try:
            if httpx.get(base + "/readyz").status_code == 200:
                break
        except httpx.TransportError:
            time.sleep(0.1)
    c = httpx.Client(base_url=base, timeout=300)
    out: dict[str, object] = {"tree": str(TREE)}
    envr = c.post("/v1/environments", json={"name": "cell", "classes": ["a", "b"]}, headers=admin)
    env_id = envr.json()["id"]
    staging = data / "files" / ".tmp"

    def multipart_stream(total: int):
        yield (
            b"--BOUND\r\nContent-Disposition: form-data; "
            b'name="archive"; filename="c.zip"\r\n'
            b"Content-Type: application/octet-stream\r\n\r\n"
        )
        block = b"x" * MB
        for _ in range(total // MB):
            yield block
        yield b"\r\n--BOUND--\r\n"

    # A. 80 MB unauthenticated multipart
    r0, _ = rss(proc.pid)
    reset_hwm(proc.pid)
    free_watch = Watch(tmp_free, "min")
    stage_watch = Watch(lambda: tree_bytes(staging), "max")
    free0 = tmp_free()
    t0 = time.monotonic()
    try:
        r = c.post(
            f"/v1/environments/{env_id}/snapshots",
            content=multipart_stream(80 * MB),
            headers={
                "Content-Type": "multipart/form-data; boundary=BOUND",
                "Content-Length": str(sum(map(len, multipart_stream(80 * MB)))),
            },
        )
        status, body = r.status_code, r.text[:150]
    except httpx.HTTPError as exc:
        status, body = "transport error", repr(exc)[:150]
    dt = time.monotonic() - t0
    time.sleep(0.1)
    out["A_unauth_80MB_multipart"] = {
        "status": status,
        "body": body,
        "seconds": round(dt, 2),
        "tmp_spooled_peak_MB": round((free0 - free_watch.done()) / MB, 1),
        "staging_peak_MB": round(stage_watch.done() / MB, 1),
        "api_rss_MB_before_after_peak": (r0, *rss(proc.pid)),
    }

    # B. 80 MB JSON with a valid key
    r0, _ = rss(proc.pid)
    reset_hwm(proc.pid)
    payload = b'{"name": "x", "classes": ["a"], "reference": {"pad": "' + b" " * (80 * MB) + b'"}}'
    t0 = time.monotonic()
    try:
        r = c.post(
            "/v1/environments",
            content=payload,
            headers={**admin, "Content-Type": "application/json"},
        )
        status, body = r.status_code, r.text[:150]
    except httpx.HTTPError as exc:
        status, body = "transport error", repr(exc)[:150]
    out["B_json_80MB"] = {
        "status": status,
        "body": body,
        "seconds": round(time.monotonic() - t0, 2),
        "api_rss_MB_before_after_peak": (r0, *rss(proc.pid)),
    }
    del payload

    def jpeg(seed, size=(64, 48), q=95):
        rng = np.random.default_rng(seed)
        b = io.BytesIO()
        Image.fromarray(rng.integers(0, 255, (size[1], size[0], 3), dtype=np.uint8)).save(
            b, "JPEG", quality=q
        )
        return b.getvalue()

    base_members = {f"cap/a{i}.jpg": jpeg(i) for i in range(3)}
    base_members["cap/a0.txt"] = b"0 0.5 0.5 0.2 0.3\n"

    # C. zip bomb: ~150 MB of zeros as one member
    zb = io.BytesIO()
    with zipfile.ZipFile(zb, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as zf:
        for k, v in base_members.items():
            zf.writestr(k, v)
        zf.writestr("cap/a9.jpg", b"\0" * (151 * 10**6))
    bomb = zb.getvalue()
    stage_watch = Watch(lambda: tree_bytes(staging), "max")
    r = c.post(
        f"/v1/environments/{env_id}/snapshots",
        files=[("archive", ("bomb.zip", bomb))],
        headers=admin,
    )
    out["C_zip_bomb"] = {
        "zip_KB": len(bomb) // 1024,
        "status": r.status_code,
        "body": r.text[:300],
        "staged_peak_MB": round(stage_watch.done() / MB, 1),
    }

    # D. tar.gz with 150k directory entries
    tb = io.BytesIO()
    with tarfile.open(fileobj=tb, mode="w:gz") as tf:
        for i in range(150_000):
            info = tarfile.TarInfo(f"d/{i}")
            info.type = tarfile.DIRTYPE
            tf.addfile(info)
        for k, v in base_members.items():
            info = tarfile.TarInfo(k)
            info.size = len(v)
            tf.addfile(info, io.BytesIO(v))
    r0, _ = rss(proc.pid)
    reset_hwm(proc.pid)
    t0 = time.monotonic()
    r = c.post(
        f"/v1/environments/{env_id}/snapshots",
        files=[("archive", ("dirs.tar.gz", tb.getvalue()))],
        headers=admin,
    )
    out["D_tar_150k_dirs"] = {
        "tar_gz_KB": len(tb.getvalue()) // 1024,
        "status": r.status_code,
        "body": r.text[:200],
        "seconds": round(time.monotonic() - t0, 2),
        "api_rss_MB_before_after_peak": (r0, *rss(proc.pid)),
    }

    # E. 7000x7000 16-bit RGBA PNG
    def chunk(kind, data):
        return (
            struct.pack(">I", len(data))
            + kind
            + data
            + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
        )

    d = zlib.compressobj(9)
    row = b"\0" * (1 + 7000 * 8)
    idat = b"".join(d.compress(row) for _ in range(7000)) + d.flush()
    png = (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", struct.pack(">IIBBBBB", 7000, 7000, 16, 6, 0, 0, 0))
        + chunk(b"IDAT", idat)
        + chunk(b"IEND", b"")
    )
    files = [("images", (f"a{i}.jpg", jpeg(i))) for i in range(3)] + [("images", ("big.png", png))]
    r = c.post(f"/v1/environments/{env_id}/snapshots", files=files, headers=admin)
    out["E_png_7000sq_16bit_rgba"] = {
        "png_KB": len(png) // 1024,
        "status": r.status_code,
        "body": r.text[:250],
    }

    # F. SQLite write lock: a large zip upload, and POST /v1/keys meanwhile
    big = io.BytesIO()
    with zipfile.ZipFile(big, "w", zipfile.ZIP_STORED) as zf:
        rng = np.random.default_rng(1)
        for i in range(990):
            b = io.BytesIO()
            Image.fromarray(rng.integers(0, 255, (72, 96, 3), dtype=np.uint8)).save(b, "PNG")
            zf.writestr(f"cap/p{i:04d}.png", b.getvalue())
            zf.writestr(f"cap/p{i:04d}.txt", b"0 0.5 0.5 0.2 0.3\n1 0.25 0.75 0.1 0.1 0.9\n" * 20)
    big_zip = big.getvalue()
    res: dict[str, object] = {}
    t_alone = time.monotonic()
    alone = c.post(
        f"/v1/environments/{env_id}/snapshots",
        files=[("archive", ("big.zip", big_zip))],
        headers=admin,
    )
    res["alone"] = (alone.status_code, round(time.monotonic() - t_alone, 2))

    def upload():
        t = time.monotonic()
        rr = c.post(
            f"/v1/environments/{env_id}/snapshots",
            files=[("archive", ("big.zip", big_zip))],
            headers=admin,
        )
        res["upload"] = (rr.status_code, round(time.monotonic() - t, 2))

    th = threading.Thread(target=upload)
    th.start()
    # wait until the staging folder appears (the body is in; the upload is being checked)
    for _ in range(20000):
        if staging.exists() and any(p.is_dir() for p in staging.iterdir()):
            break
        time.sleep(0.001)
    waits = []
    c2 = httpx.Client(base_url=base, timeout=120)
    while th.is_alive():
        t = time.monotonic()
        rk = c2.post("/v1/keys", json={"name": f"k{len(waits)}", "scopes": ["read"]}, headers=admin)
        waits.append((rk.status_code, round(time.monotonic() - t, 3)))
        time.sleep(0.05)
    th.join()
    out["F_sqlite_lock"] = {
        "zip_MB": round(len(big_zip) / MB, 1),
        "upload": res.get("upload"),
        "same_upload_alone": res.get("alone"),
        "keys_posted_during_upload": len(waits),
        "max_key_wait_s": max((w for _, w in waits), default=None),
        "key_statuses": sorted({s for s, _ in waits}),
    }
    proc.send_signal(signal.SIGTERM)
    proc.wait(10)
    shutil.rmtree(data, ignore_errors=True)
    text = json.dumps(out, indent=1)
    print(text)
    if args.out is not None:
        args.out.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
