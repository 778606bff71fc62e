"""Pose options are posted like the others: the ``pose`` key of the compare options, checked
against the generated option schema (a bad one is a 422 naming it)."""

from __future__ import annotations

from fastapi.testclient import TestClient

from tests.app.conftest import Keys


def post_environment(
    client: TestClient, keys: Keys, options: object
) -> tuple[int, dict[str, object]]:
    r = client.post(
        "/v1/environments",
        json={"name": "cell-1", "classes": ["power_drill"], "options": options},
        headers=keys.headers(),
    )
    out: dict[str, object] = r.json()
    return r.status_code, out


def test_pose_options_are_accepted_and_stored(client: TestClient, keys: Keys) -> None:
    options = {"compare": {"preset": "default", "pose": {"preset": "fast", "n_seeds": 4}}}
    status, env = post_environment(client, keys, options)
    assert status == 201, env
    assert env["options"] == options


def test_a_bad_pose_option_is_a_422_naming_it(client: TestClient, keys: Keys) -> None:
    cases = {
        "options.compare.pose: unknown pose option(s) n_seed": {"n_seed": 4},
        "options.compare.pose.max_rounds must be an integer": {"max_rounds": 1.5},
        "options.compare.pose.preset: unknown pose preset": {"preset": "slowest"},
    }
    for message, pose in cases.items():
        status, body = post_environment(client, keys, {"compare": {"pose": pose}})
        assert status == 422, body
        assert body["error"] == "InvalidInput" and message in str(body["detail"]), body
