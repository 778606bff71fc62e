"""DELETE /v1/snapshots/{id} and DELETE /v1/environments/{id} over HTTP: 204 and the files
gone, 404 for unknown or already deleted, 409 while a job uses it or for the environment's
newest reconstructed snapshot, 403 without the admin scope."""

from __future__ import annotations

from datetime import timedelta
from pathlib import Path
from typing import Any

import numpy as np
from fastapi.testclient import TestClient
from sqlalchemy.orm import Session, sessionmaker

from app.core import change_clusters, retention
from app.core.enums import ComparisonState, JobState, SnapshotState
from app.core.models import Comparison, Job, Snapshot, utcnow
from app.core.settings import get_settings
from app.core.storage import LocalStorage
from tests.app.api.test_snapshots_upload import as_parts, capture
from tests.app.conftest import Keys


def _environment(client: TestClient, keys: Keys, name: str = "line-9") -> str:
    r = client.post(
        "/v1/environments",
        json={"name": name, "classes": ["power_drill", "bowl"]},
        headers=keys.headers(),
    )
    assert r.status_code == 201, r.text
    return str(r.json()["id"])


def _upload(client: TestClient, keys: Keys, env_id: str) -> dict[str, Any]:
    r = client.post(
        f"/v1/environments/{env_id}/snapshots",
        files=as_parts(capture()),
        headers=keys.headers("capture"),
    )
    assert r.status_code == 202, r.text
    body: dict[str, Any] = r.json()
    return body


def _finish(
    factory: sessionmaker[Session], job_id: str, snapshot_id: str, state: SnapshotState
) -> None:
    """What the worker would have written: the job final and the snapshot's outcome."""
    with factory.begin() as s:
        s.get_one(Job, job_id).state = JobState.succeeded
        snap = s.get_one(Snapshot, snapshot_id)
        snap.state = state
        if state == SnapshotState.reconstructed:
            snap.pointcloud_key = f"{snap.storage_prefix}/reconstruction/cloud.ply"


def _files(snapshot_id: str) -> Path:
    return get_settings().resolved_storage_dir / "snapshots" / snapshot_id


def test_delete_snapshot(
    client: TestClient, keys: Keys, session_factory: sessionmaker[Session]
) -> None:
    env_id = _environment(client, keys)
    first = _upload(client, keys, env_id)
    snap_id, job_id = first["snapshot"]["id"], first["job"]["id"]
    assert (_files(snap_id) / "images").is_dir()
    url = f"/v1/snapshots/{snap_id}"

    r = client.delete(url, headers=keys.headers())
    assert r.status_code == 409 and r.json()["error"] == "JobsActive"
    assert job_id in r.json()["detail"]
    assert client.delete(url, headers=keys.headers("read")).status_code == 403
    assert client.delete(url, headers=keys.headers("capture")).status_code == 403

    # reconstructed and the newest: the twin stands at it
    _finish(session_factory, job_id, snap_id, SnapshotState.reconstructed)
    r = client.delete(url, headers=keys.headers())
    assert r.status_code == 409 and r.json()["error"] == "SnapshotInUse"

    # a newer reconstructed snapshot: the first one may go
    second = _upload(client, keys, env_id)
    _finish(
        session_factory,
        second["job"]["id"],
        second["snapshot"]["id"],
        SnapshotState.reconstructed,
    )
    r = client.delete(url, headers=keys.headers())
    assert r.status_code == 204 and r.content == b""
    assert not _files(snap_id).exists()
    assert (_files(second["snapshot"]["id"]) / "images").is_dir()
    assert client.get(url, headers=keys.headers("read")).status_code == 404
    assert client.get(f"/v1/jobs/{job_id}", headers=keys.headers("read")).status_code == 404
    listed = client.get(f"/v1/environments/{env_id}/snapshots", headers=keys.headers("read"))
    assert [s["id"] for s in listed.json()] == [second["snapshot"]["id"]]
    r = client.delete(url, headers=keys.headers())
    assert r.status_code == 404 and r.json()["error"] == "NotFound"
    assert client.delete("/v1/snapshots/nope", headers=keys.headers()).status_code == 404


def test_delete_environment(
    client: TestClient, keys: Keys, session_factory: sessionmaker[Session]
) -> None:
    env_id = _environment(client, keys)
    other_id = _environment(client, keys, "line-10")
    upload = _upload(client, keys, env_id)
    kept = _upload(client, keys, other_id)
    url = f"/v1/environments/{env_id}"

    r = client.delete(url, headers=keys.headers())
    assert r.status_code == 409 and r.json()["error"] == "JobsActive"
    assert client.delete(url, headers=keys.headers("read")).status_code == 403

    _finish(session_factory, upload["job"]["id"], upload["snapshot"]["id"], SnapshotState.failed)
    r = client.delete(url, headers=keys.headers())
    assert r.status_code == 204 and r.content == b""
    assert not _files(upload["snapshot"]["id"]).exists()
    assert client.get(url, headers=keys.headers("read")).status_code == 404
    r = client.get(f"/v1/snapshots/{upload['snapshot']['id']}", headers=keys.headers("read"))
    assert r.status_code == 404
    assert client.delete(url, headers=keys.headers()).status_code == 404
    # the other environment is untouched
    assert (_files(kept["snapshot"]["id"]) / "images").is_dir()
    r = client.get(f"/v1/environments/{other_id}/snapshots", headers=keys.headers("read"))
    assert [s["id"] for s in r.json()] == [kept["snapshot"]["id"]]
    # the name is free again
    assert _environment(client, keys) != env_id


def test_environment_retention_options_are_checked(client: TestClient, keys: Keys) -> None:
    good = {"images_after_days": 30, "keep_last_snapshots": 10}
    r = client.post(
        "/v1/environments",
        json={"name": "line-11", "classes": ["bowl"], "options": {"retention": good}},
        headers=keys.headers(),
    )
    assert r.status_code == 201, r.text
    assert r.json()["options"]["retention"] == good
    for bad, named in (
        ({"keep_last_snapshots": -1}, "keep_last_snapshots"),
        ({"keep_last_snapshots": 2.5}, "keep_last_snapshots"),
        ({"keep_last_snapshots": True}, "keep_last_snapshots"),
        ({"images_after_days": "30"}, "images_after_days"),
        ({"images_after_days": 1e9}, "images_after_days"),
        ({"keep_images": 3}, "keep_images"),
        ([1], "options.retention"),
    ):
        r = client.post(
            "/v1/environments",
            json={"name": "line-12", "classes": ["bowl"], "options": {"retention": bad}},
            headers=keys.headers(),
        )
        assert r.status_code == 422, (bad, r.text)
        assert named in r.json()["detail"], (bad, r.json())


def test_snapshot_says_when_its_photos_were_deleted(
    client: TestClient, keys: Keys, session_factory: sessionmaker[Session]
) -> None:
    env_id = _environment(client, keys)
    upload = _upload(client, keys, env_id)
    snap_id = upload["snapshot"]["id"]
    _finish(session_factory, upload["job"]["id"], snap_id, SnapshotState.reconstructed)
    url = f"/v1/snapshots/{snap_id}"
    assert client.get(url, headers=keys.headers("read")).json()["images_deleted_at"] is None
    storage = LocalStorage(get_settings().resolved_storage_dir)
    later = utcnow() + timedelta(days=31)
    with session_factory.begin() as s:
        counts = retention.apply_policy(s, storage, retention.Policy(images_after_days=30), later)
    assert counts["images_deleted"] == 1
    body = client.get(url, headers=keys.headers("read")).json()
    assert body["images_deleted_at"] is not None and body["state"] == "reconstructed"
    assert "pointcloud" in body["links"]
    assert not (_files(snap_id) / "images").exists() and (_files(snap_id) / "labels").is_dir()


def _compare(
    client: TestClient,
    keys: Keys,
    factory: sessionmaker[Session],
    env_id: str,
    before: str,
    after: str,
    n_points: int,
) -> str:
    """A comparison through the API, done as the worker would: its job succeeded and its
    clusters.npz (one cluster of ``n_points``) stored; returns its id."""
    r = client.post(
        f"/v1/environments/{env_id}/comparisons",
        json={"before": before, "after": after},
        headers=keys.headers(),
    )
    assert r.status_code == 202, r.text
    comparison_id = str(r.json()["id"])
    with factory.begin() as s:
        comparison = s.get_one(Comparison, comparison_id)
        s.get_one(Job, comparison.job_id).state = JobState.succeeded
        comparison.state = ComparisonState.succeeded
    points = np.zeros((n_points, 3), np.float32)
    change_clusters.write(
        LocalStorage(get_settings().resolved_storage_dir),
        change_clusters.clusters_key(f"snapshots/{after}", comparison_id),
        [change_clusters.StoredCluster(0, "added", None, n_points, points)],
    )
    return comparison_id


def test_deleting_the_before_snapshot_deletes_its_comparisons_clusters(
    client: TestClient, keys: Keys, session_factory: sessionmaker[Session]
) -> None:
    """The comparisons' cluster points lie beside the after snapshot's files; deleting the
    before snapshot deletes the comparisons and their files, the after snapshot keeps its
    own. A re-run of the same pair is a comparison with a file of its own."""
    env_id = _environment(client, keys)
    ids = []
    for _ in range(2):
        upload = _upload(client, keys, env_id)
        ids.append(upload["snapshot"]["id"])
        _finish(session_factory, upload["job"]["id"], ids[-1], SnapshotState.reconstructed)
    before, after = ids
    first = _compare(client, keys, session_factory, env_id, before, after, 3)
    rerun = _compare(client, keys, session_factory, env_id, before, after, 5)
    for comparison_id, n_points in ((first, 3), (rerun, 5)):
        r = client.get(f"/v1/comparisons/{comparison_id}/clusters", headers=keys.headers("read"))
        assert r.status_code == 200, r.text
        assert [c["n_points"] for c in r.json()["clusters"]] == [n_points]
    comparisons_dir = _files(after) / "comparisons"
    assert sorted(p.name for p in comparisons_dir.iterdir()) == sorted([first, rerun])

    r = client.delete(f"/v1/snapshots/{before}", headers=keys.headers())
    assert r.status_code == 204, r.text
    assert list(comparisons_dir.iterdir()) == []
    assert (_files(after) / "images").is_dir()
    r = client.get(f"/v1/comparisons/{first}/clusters", headers=keys.headers("read"))
    assert r.status_code == 404
