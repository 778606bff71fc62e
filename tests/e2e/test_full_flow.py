"""A small generated scene through the whole embedded service over HTTP: object library,
environment with its marker sheet, two captures reconstructed by structure from motion,
the automatic comparison, the change with its pose against the ground truth, the twin's
state (filled by the first snapshot's inventory) and the instance's history."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest

from app.client import check, embedded_service, poll_job, upload_capture
from workers.demo.evaluate import match_changes
from workers.pipeline.synth import generate, preset

pytestmark = [pytest.mark.slow, pytest.mark.e2e]
ADMIN_KEY = "td_full_flow_admin_key_0123456789"


def test_moved_object_found_with_its_pose(tmp_path: Path) -> None:
    options = preset("demo")
    options = replace(
        options,
        path=replace(options.path, n_views=16),
        camera=replace(options.camera, width=640, height=480, focal_px=520.0),
    )
    scene = tmp_path / "scene"
    generate(scene, "moved", 1, options)
    truth = json.loads((scene / "ground_truth.json").read_text())

    with embedded_service(tmp_path / "data", ADMIN_KEY, tmp_path / "service.log") as client:
        for name in truth["classes"]:
            model = (scene / "objects" / f"{name}.ply").read_bytes()
            job = check(
                client.post(
                    "/v1/objects", files={"file": (f"{name}.ply", model)}, data={"name": name}
                ),
                202,
            )["job"]
            assert poll_job(client, job["id"], name, 300, quiet=True)["state"] == "succeeded"
        env = check(
            client.post(
                "/v1/environments",
                json={"name": "cell", "classes": truth["classes"], "reference": truth["reference"]},
            ),
            201,
        )
        snapshots = []
        for capture in ("before", "after"):
            accepted = upload_capture(client, env["id"], scene / capture)
            job = poll_job(client, accepted["job"]["id"], capture, 600, quiet=True)
            assert job["state"] == "succeeded", job
            snapshots.append(check(client.get(f"/v1/snapshots/{accepted['snapshot']['id']}"), 200))
        quality = snapshots[1]["quality"]
        assert quality["images_registered"] == 16
        assert quality["marker_residual_m"] < 0.005
        assert snapshots[0]["comparison"] is None and snapshots[1]["comparison"]

        comparison_id = snapshots[1]["comparison"]
        job_id = check(client.get(f"/v1/comparisons/{comparison_id}"), 200)["job"]
        assert poll_job(client, job_id, "compare", 300, quiet=True)["state"] == "succeeded"
        comparison = check(client.get(f"/v1/comparisons/{comparison_id}"), 200)
        state = check(client.get(f"/v1/environments/{env['id']}/state"), 200)

        matches, extra = match_changes(truth, comparison["changes"])
        assert extra == [], [(e["type"], e.get("identification"), e["cluster"]) for e in extra]
        (match,) = matches
        assert match.found is not None, comparison["changes"]
        found = match.found
        assert found["identification"]["metric"] > 0.5
        assert found["pose"] is not None and match.translation_error_m is not None
        quality = {k: v for k, v in found["pose_quality"].items() if k != "equivalent_poses"}
        accurate = match.translation_error_m < 0.01 and (match.rotation_error_deg or 0) < 3.0
        # The service's promise: a pose it publishes as verified is right. (How often the
        # pose is right on this small scene is measured in the closing notes and the bench:
        # this near-symmetric bracket is sometimes registered turned over, and flagged.)
        if quality["verified"]:
            assert accurate, (match.translation_error_m, match.rotation_error_deg, quality)
        else:
            assert quality["reasons"], quality
        print(
            f"pose error {match.translation_error_m * 1000:.1f} mm "
            f"{match.rotation_error_deg:.2f}°, verified {quality['verified']}"
        )
        assert {c["side"] for c in comparison["clusters"]} >= {"added"}
        assert comparison["distances"]["added"]["threshold"] > 0

        # the twin: the first snapshot's inventory fills it; the move moves that instance
        # (or creates it, where the inventory did not find the object)
        assert {o["object"] for o in state["objects"]} <= set(truth["classes"])
        moved = truth["changes"][0]["object"]
        (instance,) = [o for o in state["objects"] if o["object"] == moved]
        assert instance["pose"] == found["pose"]
        history = check(
            client.get(f"/v1/environments/{env['id']}/objects/{instance['instance_id']}/history"),
            200,
        )
        records = [(p["snapshot"], p["change_type"]) for p in history["poses"]]
        assert records[-1] == (snapshots[1]["id"], "moved"), records
        assert records[:-1] in ([], [(snapshots[0]["id"], "inventoried")]), records
