"""Inventory options are posted like the other stages': an environment's ``inventory``
section (a preset, overrides, compare overrides under ``compare``, pose options under
``pose``), checked against the generated option schema, so a bad one is a 422 naming it."""

from __future__ import annotations

from fastapi.testclient import TestClient

from tests.app.api.test_pose_options import post_environment
from tests.app.conftest import Keys


def test_inventory_options_are_accepted_and_stored(client: TestClient, keys: Keys) -> None:
    options = {
        "reconstruct": {"preset": "fast"},
        "inventory": {
            "preset": "fast",
            "band_min_m": 0.006,
            "level_supports": False,
            "compare_preset": "lod",
            "compare": {
                "instance_match_min": 0.3,
                "threshold": {"kind": "fixed", "distance": 0.02},
            },
            "pose": {"preset": "thorough", "n_seeds": 4},
        },
    }
    status, env = post_environment(client, keys, options)
    assert status == 201, env
    assert env["options"] == options
    got = client.get(f"/v1/environments/{env['id']}", headers=keys.headers("read")).json()
    assert got["options"] == options


def test_a_bad_inventory_option_is_a_422_naming_it(client: TestClient, keys: Keys) -> None:
    cases: dict[str, object] = {
        "options.inventory.preset: unknown inventory preset 'slowest'; known: default, fast": {
            "preset": "slowest"
        },
        "options.inventory: unknown inventory option(s) band": {"band": 0.01},
        "options.inventory.band_min_m must be a finite number": {"band_min_m": "4 mm"},
        "options.inventory.max_support_peaks must be an integer": {"max_support_peaks": 2.5},
        "options.inventory.level_supports must be a bool": {"level_supports": 1},
        "options.inventory.compare_preset must be one of default, lod, thesis": {
            "compare_preset": "strict"
        },
        "options.inventory.compare: unknown compare option(s) preset": {
            "compare": {"preset": "lod"}
        },
        "options.inventory.compare: unknown compare option(s) pose": {
            "compare": {"pose": {"preset": "fast"}}
        },
        "options.inventory.compare.threshold: unknown threshold key(s) sigma": {
            "compare": {"threshold": {"kind": "mean_std", "sigma": 1.0}}
        },
        "options.inventory.pose: unknown pose option(s) n_seed": {"pose": {"n_seed": 4}},
        "options.inventory.pose.preset: unknown pose preset 'slowest'": {
            "pose": {"preset": "slowest"}
        },
        "options.inventory.compare must be an object": {"compare": [1]},
        "options.inventory must be an object": ["fast"],
    }
    for message, inventory in cases.items():
        status, body = post_environment(client, keys, {"inventory": inventory})
        assert status == 422, (inventory, body)
        assert body["error"] == "InvalidInput" and message in str(body["detail"]), body
    listed = client.get("/v1/environments", headers=keys.headers("read")).json()
    assert listed == []  # nothing was created


def test_an_unknown_section_names_the_inventory_among_the_known(
    client: TestClient, keys: Keys
) -> None:
    status, body = post_environment(client, keys, {"inventories": {}})
    assert status == 422, body
    assert "known: reconstruct, compare, inventory, retention" in str(body["detail"]), body
