"""A small generated scene through the whole embedded service over HTTP: object library,
environment with its marker sheet, two captures reconstructed by structure from motion,
the automatic comparison, the change with its pose against the ground truth, the twin's
state (filled by the first snapshot's inventory) and the instance's history. The scene is
processed once per session by conftest's small_scene, which the console's tests share."""

from __future__ import annotations

import httpx
import pytest

from app.client import check
from tests.e2e.console_fixtures import ProcessedScene
from workers.demo.evaluate import match_changes

pytestmark = [pytest.mark.slow, pytest.mark.e2e, pytest.mark.timeout(900)]


def test_moved_object_found_with_its_pose(
    embedded_api: httpx.Client, small_scene: ProcessedScene
) -> None:
    # small_scene: the 16-view 640x480 scene's library objects, environment and two
    # captures went through the service and every job succeeded
    client, truth = embedded_api, small_scene.truth
    snapshots = [check(client.get(f"/v1/snapshots/{s}"), 200) for s in small_scene.snapshot_ids]
    quality = snapshots[1]["quality"]
    assert quality["images_registered"] == 16
    assert quality["marker_residual_m"] < 0.005
    assert snapshots[0]["comparison"] is None and snapshots[1]["comparison"]

    comparison_id = snapshots[1]["comparison"]
    assert comparison_id == small_scene.comparison_id
    job_id = check(client.get(f"/v1/comparisons/{comparison_id}"), 200)["job"]
    assert check(client.get(f"/v1/jobs/{job_id}"), 200)["state"] == "succeeded"
    comparison = check(client.get(f"/v1/comparisons/{comparison_id}"), 200)
    env_id = small_scene.environment_id
    state = check(client.get(f"/v1/environments/{env_id}/state"), 200)

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
        client.get(f"/v1/environments/{env_id}/objects/{instance['instance_id']}/history"),
        200,
    )
    records = [(p["snapshot"], p["change_type"]) for p in history["poses"]]
    assert records[-1] == (snapshots[1]["id"], "moved"), records
    assert records[:-1] in ([], [(snapshots[0]["id"], "inventoried")]), records
