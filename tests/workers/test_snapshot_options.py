"""The snapshot job hands the stages the options of its environment: the reconstruct
section to reconstruction, the inventory section (preset, overrides, compare and pose
options) to the inventory stage, and keeps the inventory's options in the snapshot's
inventory summary. Production glue, fake pipeline, a real environment posted through the
API (PostgreSQL and SQLite)."""

from __future__ import annotations

from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy.orm import Session, sessionmaker

from app.core.models import Snapshot
from tests.app.conftest import Keys, SentTasks
from tests.app.core.test_twin_order import snapshot_job, upload
from tests.workers import fake_pipeline
from workers import snapshot as snapshot_glue
from workers.pipeline.errors import PipelineError
from workers.pipeline.inventory import InventoryOptions, inventory_options_from_json
from workers.pipeline.pose.options import pose_options_from_json
from workers.pipeline.reconstruct.options import ReconstructOptions, options_from_preset

CLASSES = ["drill", "bowl", "mug"]


def run_snapshot(
    client: TestClient,
    keys: Keys,
    factory: sessionmaker[Session],
    monkeypatch: pytest.MonkeyPatch,
    options: dict[str, Any] | None,
) -> tuple[dict[str, Any], Snapshot]:
    """Post an environment with ``options``, upload one capture, run its snapshot job; the
    options each stage was called with, and the snapshot row."""
    fake_pipeline.install(monkeypatch.setattr)
    seen: dict[str, Any] = {}

    def reconstruct(*, options: ReconstructOptions, **kwargs: Any) -> Any:
        seen["reconstruct"] = options
        return fake_pipeline.reconstruct(options=options, **kwargs)

    def take_inventory(*args: Any) -> Any:
        seen["inventory"] = args[4]
        return fake_pipeline.take_inventory(*args)

    monkeypatch.setattr(snapshot_glue, "reconstruct", reconstruct)
    monkeypatch.setattr(snapshot_glue, "take_inventory", take_inventory)
    r = client.post(
        "/v1/environments",
        json={"name": "cell-3", "classes": CLASSES, "options": options},
        headers=keys.headers(),
    )
    assert r.status_code == 201, r.text
    snap_id = upload(client, keys, r.json()["id"], {"drill": 0.2}, tag="inventory-")
    assert snapshot_glue.run(snapshot_job(factory, snap_id)) == "succeeded"
    with factory() as s:
        snap = s.get(Snapshot, snap_id)
        assert snap is not None
        s.expunge(snap)
    return seen, snap


def test_the_environments_inventory_options_reach_the_stage(
    client: TestClient,
    keys: Keys,
    session_factory: sessionmaker[Session],
    sent_tasks: SentTasks,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    inventory = {
        "preset": "fast",
        "band_min_m": 0.006,
        "compare_preset": "lod",
        "compare": {"instance_match_min": 0.3},
        "pose": {"preset": "thorough", "n_seeds": 4},
    }
    options = {"reconstruct": {"preset": "fast", "mvs_scale": 0.25}, "inventory": inventory}
    seen, snap = run_snapshot(client, keys, session_factory, monkeypatch, options)

    assert seen["reconstruct"] == options_from_preset("fast", mvs_scale=0.25)
    chosen = seen["inventory"]
    assert chosen == inventory_options_from_json(inventory)
    assert chosen != InventoryOptions()
    assert chosen.band_min_m == 0.006
    assert chosen.compare_options().threshold.kind == "lod"
    assert chosen.compare_options().instance_match_min == 0.3
    assert chosen.pose_options() == pose_options_from_json({"preset": "thorough", "n_seeds": 4})
    assert chosen.pose_options().n_seeds == 4
    assert snap.inventory is not None
    assert snap.inventory["options"] == inventory
    assert snap.inventory["objects"] == 1  # the fake stage ran: one drill


def test_without_an_inventory_section_the_stage_runs_the_default_preset(
    client: TestClient,
    keys: Keys,
    session_factory: sessionmaker[Session],
    sent_tasks: SentTasks,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    seen, snap = run_snapshot(client, keys, session_factory, monkeypatch, None)
    assert seen["reconstruct"] == options_from_preset("default")
    assert seen["inventory"] == InventoryOptions()
    assert snap.inventory is not None and snap.inventory["options"] == {"preset": "default"}


def test_the_snapshot_shows_its_inventory_summary(
    client: TestClient,
    keys: Keys,
    session_factory: sessionmaker[Session],
    sent_tasks: SentTasks,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """GET /v1/snapshots/{id} carries the summary and links the objects; a stage that
    failed shows its error, no objects link, and the objects route answers 409."""
    inventory = {"preset": "fast"}
    _, snap = run_snapshot(client, keys, session_factory, monkeypatch, {"inventory": inventory})
    read = keys.headers("read")
    got = client.get(f"/v1/snapshots/{snap.id}", headers=read).json()
    assert got["inventory"] == snap.inventory
    assert got["inventory"]["options"] == inventory and got["inventory"]["objects"] == 1
    assert got["links"]["objects"] == f"/v1/snapshots/{snap.id}/objects"
    objects = client.get(got["links"]["objects"], headers=read).json()
    assert [o["object"] for o in objects] == ["drill"]

    def failing(*args: Any) -> Any:
        raise PipelineError("no support surface", code="NoSupports")

    fake_pipeline.install(monkeypatch.setattr)
    monkeypatch.setattr(snapshot_glue, "take_inventory", failing)
    env_id = client.get(f"/v1/snapshots/{snap.id}", headers=read).json()["environment"]
    snap_id = upload(client, keys, env_id, {"drill": 0.3}, tag="inventory-b")
    assert snapshot_glue.run(snapshot_job(session_factory, snap_id)) == "succeeded"
    got = client.get(f"/v1/snapshots/{snap_id}", headers=read).json()
    assert got["inventory"] == {
        "options": inventory,
        "error": {"code": "NoSupports", "detail": "no support surface"},
        "objects": 0,
    }
    assert "objects" not in got["links"]
    r = client.get(f"/v1/snapshots/{snap_id}/objects", headers=read)
    assert r.status_code == 409 and r.json()["error"] == "NotInventoried", r.text
    assert "no support surface" in r.json()["detail"]
