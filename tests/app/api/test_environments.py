"""Environments over HTTP: creation, validation, auth scopes, and the read endpoints."""

from __future__ import annotations

import numpy as np
from fastapi.testclient import TestClient

from tests.app.conftest import Keys

MARKERS = {
    "markers": {
        "dictionary": "DICT_4X4_50",
        "size": 0.15,
        "poses": {"0": np.eye(4).tolist(), "3": np.eye(4).tolist()},
    }
}


def create(client: TestClient, keys: Keys, **body: object) -> dict[str, object]:
    payload = {"name": "line-1", "classes": ["power_drill", "bowl"], **body}
    r = client.post("/v1/environments", json=payload, headers=keys.headers())
    assert r.status_code == 201, r.text
    out: dict[str, object] = r.json()
    return out


def test_create_and_read(client: TestClient, keys: Keys) -> None:
    env = create(client, keys, reference=MARKERS)
    assert env["classes"] == ["power_drill", "bowl"]
    r = client.get(f"/v1/environments/{env['id']}", headers=keys.headers("read"))
    assert r.status_code == 200 and r.json()["reference"]["markers"]["size"] == 0.15
    listed = client.get("/v1/environments", headers=keys.headers("read")).json()
    assert [e["id"] for e in listed] == [env["id"]]
    for path in ("snapshots", "comparisons"):
        r = client.get(f"/v1/environments/{env['id']}/{path}", headers=keys.headers("read"))
        assert r.status_code == 200 and r.json() == []
    state = client.get(f"/v1/environments/{env['id']}/state", headers=keys.headers("read"))
    twin = {"seq": 0, "snapshot": None, "status": "current", "waiting_for": None}
    twin["comparison"] = None
    assert state.json() == {
        "environment": env["id"],
        "objects": [],
        "twin": twin,
        "at_snapshot": None,
    }


def test_auth_missing_wrong_and_scope(client: TestClient, keys: Keys) -> None:
    body = {"name": "x", "classes": ["a"]}
    r = client.post("/v1/environments", json=body)
    assert r.status_code == 401 and r.json()["error"] == "Unauthorized"
    r = client.post("/v1/environments", json=body, headers={"Authorization": "Bearer td_nope"})
    assert r.status_code == 401
    r = client.post("/v1/environments", json=body, headers=keys.headers("read"))
    assert r.status_code == 403 and r.json()["error"] == "Forbidden"
    r = client.get("/v1/environments", headers=keys.headers("capture"))
    assert r.status_code == 403
    assert client.get("/healthz").status_code == 200


def test_duplicate_name_conflicts(client: TestClient, keys: Keys) -> None:
    create(client, keys)
    r = client.post(
        "/v1/environments", json={"name": "line-1", "classes": ["a"]}, headers=keys.headers()
    )
    assert r.status_code == 409 and r.json()["error"] == "EnvironmentExists"


def test_bad_reference_and_classes_are_422(client: TestClient, keys: Keys) -> None:
    bad_pose = {"markers": {"size": 0.15, "poses": {"0": [[1, 0, 0], [0, 1, 0]]}}}
    r = client.post(
        "/v1/environments",
        json={"name": "a", "classes": ["x"], "reference": bad_pose},
        headers=keys.headers(),
    )
    assert r.status_code == 422 and "reference.markers.poses[0]" in r.json()["detail"]
    scaled = np.eye(4) * 2
    scaled[3, 3] = 1
    r = client.post(
        "/v1/environments",
        json={
            "name": "a",
            "classes": ["x"],
            "reference": {"markers": {"size": 0.1, "poses": {"1": scaled.tolist()}}},
        },
        headers=keys.headers(),
    )
    assert r.status_code == 422 and "rotation" in r.json()["detail"]
    r = client.post(
        "/v1/environments", json={"name": "a", "classes": ["x", "x"]}, headers=keys.headers()
    )
    assert r.status_code == 422 and "duplicate" in r.json()["detail"]
    r = client.post("/v1/environments", json={"name": "a"}, headers=keys.headers())
    assert r.status_code == 422 and r.json()["error"] == "InvalidInput"


def test_unknown_ids_are_404(client: TestClient, keys: Keys) -> None:
    for path in (
        "/v1/environments/nope",
        "/v1/jobs/nope",
        "/v1/snapshots/nope",
        "/v1/comparisons/nope",
        "/v1/objects/nope",
    ):
        r = client.get(path, headers=keys.headers("read"))
        assert r.status_code == 404 and r.json()["error"] == "NotFound", path


def test_bad_pipeline_options_are_422_naming_the_option(client: TestClient, keys: Keys) -> None:
    """Options are checked against the workers' option names, presets and types when the
    environment is posted (a job used to fail on them later); good ones are stored as given."""
    cases = {
        "options.reconstruct.cuda_dense must be a bool": {"reconstruct": {"cuda_dense": "yes"}},
        "options.reconstruct: unknown reconstruct option(s) bogus": {"reconstruct": {"bogus": 1}},
        "unknown reconstruct preset 'best'": {"reconstruct": {"preset": "best"}},
        "options.reconstruct.planar_min_points must be an integer": {
            "reconstruct": {"planar_min_points": 2.5}
        },
        "options.compare.threshold: unknown threshold key(s) sigma": {
            "compare": {"threshold": {"kind": "mean_std", "sigma": 1}}
        },
        "options.compare.threshold.kind must be one of mean_std, fixed, lod": {
            "compare": {"threshold": {"kind": "median"}}
        },
        "options.compare.stats_region must be one of overlap, all": {
            "compare": {"stats_region": "some"}
        },
        "unknown options section(s) posing": {"posing": {}},
        "options.compare must be an object": {"compare": [1]},
    }
    for message, options in cases.items():
        r = client.post(
            "/v1/environments",
            json={"name": "a", "classes": ["x"], "options": options},
            headers=keys.headers(),
        )
        assert r.status_code == 422, (options, r.text)
        assert r.json()["error"] == "InvalidInput" and message in r.json()["detail"], r.text
    good = {
        "reconstruct": {"preset": "fast", "mvs_scale": 1, "cuda_dense": False},
        "compare": {"threshold": {"kind": "lod", "registration": None}, "grow_threshold": None},
    }
    env = create(client, keys, options=good)
    assert env["options"] == good
    assert client.get("/v1/environments", headers=keys.headers("read")).json()[0]["id"] == env["id"]
