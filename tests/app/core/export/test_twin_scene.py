"""The twin scene's rules that need no library model: which instances are not drawn and
why, and which snapshots a past state can be asked at."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from sqlalchemy.orm import Session

from app.core.enums import SnapshotState, TwinUpdate
from app.core.errors import Conflict, NotFound
from app.core.export import twin_scene
from app.core.models import Environment, Snapshot, new_id, utcnow
from app.core.storage import LocalStorage
from tests.app.core.export.test_gltf import gltf_json
from tests.app.core.export.validator import assert_valid


def row(pose: list[list[float]] | None) -> twin_scene.InstanceState:
    return twin_scene.InstanceState(
        instance_id=new_id(),
        object_name="drill",
        object_id=None,
        pose=pose,
        pose_quality=None,
        since_snapshot="s",
        created_snapshot="s",
        created_at=utcnow(),
    )


def test_instances_without_a_rigid_pose_are_listed_not_drawn(
    session: Session, tmp_path: Path
) -> None:
    scaled = (np.eye(4) * [2, 2, 2, 1]).tolist()
    mirrored = np.diag([1.0, 1.0, -1.0, 1.0]).tolist()
    nan = np.full((4, 4), np.nan).tolist()
    rows = [row(None), row(scaled), row(mirrored), row(nan)]
    view = twin_scene.TwinView("env", "snap", 2, False, rows)
    data = twin_scene.glb(session, LocalStorage(tmp_path / "store"), view)
    (tmp_path / "undrawn.glb").write_bytes(data)
    assert_valid(tmp_path / "undrawn.glb")
    [root] = gltf_json(data)["nodes"]
    assert [(u["instance_id"], u["reason"]) for u in root["extras"]["undrawn"]] == [
        (rows[0].instance_id, "pose unknown"),
        (rows[1].instance_id, "pose is not a rigid transform"),
        (rows[2].instance_id, "pose is not a rigid transform"),
        (rows[3].instance_id, "pose is not a finite 4x4 matrix"),
    ]
    assert root["extras"]["snapshot"] == "snap" and root["extras"]["seq"] == 2


@pytest.mark.parametrize(
    ("state", "update", "error", "message"),
    [
        (SnapshotState.reconstructed, None, Conflict, "has not reached it yet"),
        (SnapshotState.failed, TwinUpdate.skipped, Conflict, "skipped it (state failed)"),
        (SnapshotState.deleted, TwinUpdate.applied, NotFound, "not found in environment"),
    ],
)
def test_a_past_state_is_only_at_a_snapshot_the_twin_reflects(
    session: Session,
    state: SnapshotState,
    update: TwinUpdate | None,
    error: type[Exception],
    message: str,
) -> None:
    env = Environment(name=f"env-{new_id()[:8]}", classes=["drill"])
    session.add(env)
    session.flush()
    snap = Snapshot(
        environment_id=env.id, seq=1, storage_prefix="p", state=state, twin_update=update
    )
    session.add(snap)
    session.flush()
    with pytest.raises(error, match=re.escape(message)):
        twin_scene.view(session, env, snap.id)
