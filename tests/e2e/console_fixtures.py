"""A small generated scene processed by the real embedded service (shared by the full flow
and the console's browser tests through tests/e2e/conftest.py), API keys. Building the
console and launching Chromium live in bench/console_browser.py (the benchmark uses them
too)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx

from app.client import check, poll_job, upload_capture
from bench.loopback import generate_world

SHOTS_DIR = Path("/tmp/console-shots")
EMBEDDED_ADMIN_KEY = "td_embedded_e2e_admin_key_0123456789"  # conftest's embedded_api


@dataclass(frozen=True)
class ProcessedScene:
    """One environment with two reconstructed captures of a generated 'moved' scene and
    their automatic comparison, done."""

    environment_id: str
    snapshot_ids: list[str]
    comparison_id: str
    truth: dict[str, Any]
    scene_dir: Path  # the generated scene: before/, after/ capture folders, objects/


def process_small_scene(client: httpx.Client, work: Path, name: str = "cell") -> ProcessedScene:
    """Generate a 16-view 640x480 scene with one moved object, upload the library objects and
    both captures through ``client`` (admin), wait for the reconstructions and the
    automatic comparison; raises AssertionError when a job does not succeed."""
    scene = work / "scene"
    if not (scene / "ground_truth.json").exists():
        generate_world(scene, "moved", 1, 16, (640, 480), 520.0)
    truth = json.loads((scene / "ground_truth.json").read_text())
    for cls in truth["classes"]:
        model = (scene / "objects" / f"{cls}.ply").read_bytes()
        job = check(
            client.post("/v1/objects", files={"file": (f"{cls}.ply", model)}, data={"name": cls}),
            202,
        )["job"]
        assert poll_job(client, job["id"], cls, 300, quiet=True)["state"] == "succeeded"
    env = check(
        client.post(
            "/v1/environments",
            json={"name": name, "classes": truth["classes"], "reference": truth["reference"]},
        ),
        201,
    )
    snapshot_ids = []
    for capture in ("before", "after"):
        accepted = upload_capture(client, env["id"], scene / capture)
        job = poll_job(client, accepted["job"]["id"], capture, 900, quiet=True)
        assert job["state"] == "succeeded", job
        snapshot_ids.append(accepted["snapshot"]["id"])
    comparison_id = check(client.get(f"/v1/snapshots/{snapshot_ids[1]}"), 200)["comparison"]
    assert comparison_id, "the second snapshot has no automatic comparison"
    job_id = check(client.get(f"/v1/comparisons/{comparison_id}"), 200)["job"]
    assert poll_job(client, job_id, "compare", 600, quiet=True)["state"] == "succeeded"
    return ProcessedScene(env["id"], snapshot_ids, comparison_id, truth, scene)


def create_key(client: httpx.Client, name: str, scopes: list[str]) -> str:
    """A new API key's token (``client`` holds an admin key)."""
    body = check(client.post("/v1/keys", json={"name": name, "scopes": scopes}), 201)
    token: str = body["key"]
    return token
