"""`make serve`'s processes (embedded: SQLite, file-system broker, local storage) driven
over real HTTP: create an environment, upload a capture, poll its job to the end, cancel
another, prepare a library object."""

from __future__ import annotations

import json
import os
import signal
import sys
from collections.abc import Callable
from pathlib import Path

import httpx
import pytest

from app.client import capture_parts
from tests.e2e.conftest import Processes, api_client, free_port, poll_job
from workers.pipeline.synth import PRESETS, generate

pytestmark = [pytest.mark.slow, pytest.mark.e2e]


def capture_files(capture_dir: Path) -> list[tuple[str, tuple[str, bytes]]]:
    return [(field, (p.name, p.read_bytes())) for field, p in capture_parts(capture_dir)]


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("scene")
    generate(out, "moved", seed=3, options=PRESETS["tiny"])
    return out


def test_embedded_serve_end_to_end(
    tmp_path: Path, tiny_scene: Path, processes: Callable[..., Processes]
) -> None:
    procs = processes()
    port = free_port()
    procs.start("serve", [sys.executable, "-m", "app.cli", "serve", "--port", str(port)])
    client = api_client(port)

    classes = (tiny_scene / "before" / "classes.txt").read_text().split()
    reference = json.loads((tiny_scene / "reference.json").read_text())
    env = client.post(
        "/v1/environments", json={"name": "cell", "classes": classes, "reference": reference}
    )
    assert env.status_code == 201, env.text
    env_id = env.json()["id"]

    first = client.post(
        f"/v1/environments/{env_id}/snapshots", files=capture_files(tiny_scene / "before")
    )
    assert first.status_code == 202, first.text
    assert first.headers["location"] == f"/v1/jobs/{first.json()['job']['id']}"
    job = poll_job(client, first.json()["job"]["id"], 240)
    assert job["state"] in {"succeeded", "failed"}, job
    snap = client.get(f"/v1/snapshots/{first.json()['snapshot']['id']}").json()
    assert snap["n_images"] == len(list((tiny_scene / "before" / "images").iterdir()))
    if job["state"] == "failed":  # a failure must say why, in the job and on the snapshot
        assert job["error"]["code"] and snap["state"] == "failed"
    else:
        assert snap["state"] == "reconstructed" and snap["quality"]["points"] > 0
        cloud = client.get(f"/v1/snapshots/{snap['id']}/pointcloud")
        assert cloud.status_code == 200 and cloud.content.startswith(b"ply")

    second = client.post(
        f"/v1/environments/{env_id}/snapshots", files=capture_files(tiny_scene / "after")
    )
    assert second.status_code == 202, second.text
    job_id = second.json()["job"]["id"]
    cancel = client.post(f"/v1/jobs/{job_id}/cancel")
    assert cancel.status_code == 200, cancel.text
    job = poll_job(client, job_id, 120)
    assert job["state"] == "cancelled", job
    snap2 = client.get(f"/v1/snapshots/{second.json()['snapshot']['id']}").json()
    assert snap2["state"] == "cancelled", snap2  # queued or running, the snapshot ends too
    assert client.post(f"/v1/jobs/{job_id}/cancel").status_code == 409

    history = client.get(f"/v1/environments/{env_id}/snapshots").json()
    assert [s["seq"] for s in history] == [2, 1]

    model = (tiny_scene / "objects" / f"{classes[0]}.ply").read_bytes()
    obj = client.post(
        "/v1/objects", files={"file": (f"{classes[0]}.ply", model)}, data={"name": classes[0]}
    )
    assert obj.status_code == 202, obj.text
    assert poll_job(client, obj.json()["job"]["id"], 120)["state"] == "succeeded"
    ready = client.get(f"/v1/objects/{obj.json()['id']}").json()
    assert ready["state"] == "ready" and ready["diameter_m"] > 0.05

    unauth = httpx.get(f"http://127.0.0.1:{port}/v1/environments")
    assert unauth.status_code == 401

    # A crashed CPU worker is restarted by `serve`, and work goes on.
    serve_pid = procs.procs["serve"].pid
    cpu = [p for p in children(serve_pid) if "-Q cpu" in cmdline(p)]
    assert len(cpu) == 1
    for pid in [*children(cpu[0]), cpu[0]]:
        os.kill(pid, signal.SIGKILL)
    obj2 = client.post(
        "/v1/objects", files={"file": (f"{classes[1]}.ply", model)}, data={"name": classes[1]}
    )
    assert obj2.status_code == 202, obj2.text
    assert poll_job(client, obj2.json()["job"]["id"], 180)["state"] == "succeeded"


def children(pid: int) -> list[int]:
    out = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                out.append(int(entry.name))
    return out


def cmdline(pid: int) -> str:
    return (Path("/proc") / str(pid) / "cmdline").read_bytes().replace(b"\0", b" ").decode()
