"""The twin and the snapshots' inventories (app.core.inventory through app.core.twin.advance):
the first snapshot fills the twin, taking over a seeded instance where it stands; a later
one confirms what it sees, refreshes a pose only beyond the estimate's noise (an unverified
estimate only where the twin's own pose is one too), and adds what no instance accounts
for."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from sqlalchemy import select
from sqlalchemy.orm import Session

from app.core import inventory, twin
from app.core.enums import ComparisonState, SnapshotState, TwinEdit
from app.core.models import (
    Change,
    Comparison,
    Environment,
    Event,
    InstancePose,
    LibraryObject,
    Snapshot,
    TwinInstance,
    new_id,
)


def pose_at(x: float, y: float = 0.0, yaw_deg: float = 0.0) -> list[list[float]]:
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    m = np.eye(4)
    m[:2, :2] = [[c, -s], [s, c]]
    m[:3, 3] = [x, y, 0.0]
    return m.tolist()


def found(name: str, pose: list[list[float]], verified: bool = True) -> dict[str, Any]:
    return {
        "object": name,
        "pose": pose,
        "pose_quality": {"verified": verified, "reasons": []},
        "identification": {"metric": 0.8, "iou": 0.8, "overlaps": 9, "occurrences": 10},
        "centroid_env": [pose[0][3], pose[1][3], 0.05],
        "support": "floor",
    }


@pytest.fixture
def env(session: Session) -> Environment:
    tag = new_id()[:8]
    environment = Environment(name=f"env-{tag}", classes=["drill", "bowl"])
    session.add(environment)
    for name, diameter in (("drill", 0.2), ("bowl", 0.16)):
        session.add(
            LibraryObject(
                name=name,
                filename="m.ply",
                file_key="k",
                size_bytes=1,
                diameter_m=diameter,
            )
        )
    session.flush()
    return environment


def snapshot(session: Session, env: Environment, seq: int) -> Snapshot:
    snap = Snapshot(
        environment_id=env.id, seq=seq, storage_prefix=f"p/{seq}", state=SnapshotState.processing
    )
    session.add(snap)
    session.flush()
    return snap


def reconstructed(session: Session, snap: Snapshot, objects: list[dict[str, Any]]) -> None:
    """What the snapshot job persists: the inventory, the state, then the chain moves on."""
    inventory.record(session, snap, objects, {"stats": {"objects": len(objects)}})
    snap.state = SnapshotState.reconstructed
    session.flush()
    twin.advance(session, snap.environment_id)


def succeed_comparison(
    session: Session,
    env: Environment,
    before: Snapshot,
    after: Snapshot,
    changes: list[dict[str, Any]] = (),  # type: ignore[assignment]
) -> None:
    """The automatic comparison of ``after`` succeeds with ``changes`` (Change columns)."""
    comparison = session.scalar(
        select(Comparison).where(Comparison.after_id == after.id, Comparison.automatic.is_(True))
    )
    assert comparison is not None and comparison.before_id == before.id
    for position, change in enumerate(changes):
        comparison.changes.append(Change(position=position, **change))
    comparison.state = ComparisonState.succeeded
    session.flush()
    twin.advance(session, env.id)


def seed_bowl(session: Session, env: Environment, x: float, external_id: str) -> TwinInstance:
    """An open bowl instance at ``x`` the twin platform gave (``external_id``)."""
    seeded = TwinInstance(
        environment_id=env.id, object_name="bowl", pose=pose_at(x), external_id=external_id
    )
    session.add(seeded)
    session.flush()
    return seeded


def x_of(instance: TwinInstance) -> float:
    assert instance.pose is not None
    return instance.pose[0][3]


def history(session: Session, instance_id: str) -> list[str]:
    return [
        p.change_type
        for p in session.scalars(
            select(InstancePose)
            .where(InstancePose.instance_id == instance_id)
            .order_by(InstancePose.created_at, InstancePose.id)
        )
    ]


def test_first_snapshot_fills_the_twin_and_later_ones_confirm_it(
    session: Session, env: Environment
) -> None:
    seeded = seed_bowl(session, env, 0.52, "erp:1")
    session.add(InstancePose(instance_id=seeded.id, change_type=TwinEdit.seeded, pose=seeded.pose))
    first = snapshot(session, env, 1)
    reconstructed(
        session,
        first,
        [found("drill", pose_at(0.1)), found("drill", pose_at(-0.6)), found("bowl", pose_at(0.5))],
    )
    current = twin.current(session, env.id)
    assert sorted((i.object_name, x_of(i)) for i in current) == [
        ("bowl", 0.5),
        ("drill", -0.6),
        ("drill", 0.1),
    ]
    assert len(current) == 3  # the seeded bowl was taken over, not duplicated
    bowl = next(i for i in current if i.object_name == "bowl")
    assert bowl.id == seeded.id and bowl.external_id == "erp:1"
    assert history(session, bowl.id) == ["seeded", "inventoried"]
    drills = [i for i in current if i.object_name == "drill"]
    assert all(history(session, i.id) == ["inventoried"] for i in drills)
    assert {i.created_snapshot_id for i in drills} == {first.id}
    rows = inventory.objects_of(session, first.id)
    assert {r.instance_id for r in rows} == {i.id for i in current}
    event = session.scalars(
        select(Event).where(Event.environment_id == env.id).order_by(Event.created_at.desc())
    ).first()
    assert event is not None and event.data["outcome"] == "baseline"
    assert {(i["instance_id"], i["external_id"]) for i in event.data["instances"]} >= {
        (seeded.id, "erp:1")
    }

    # seq 2: the comparison found nothing (drifts under its threshold); the inventory sees
    # the first drill 2 mm off (noise: no record), the bowl 3 cm off (a drift: refreshed),
    # a new drill and a new bowl where no instance stands, a bowl it could not pose, and
    # not the second drill (not seen)
    second = snapshot(session, env, 2)
    reconstructed(
        session,
        second,
        [
            found("drill", pose_at(0.102)),
            found("bowl", pose_at(0.53, yaw_deg=1.0)),
            found("drill", pose_at(1.5)),
            found("bowl", pose_at(-1.5), verified=False),
            {**found("bowl", pose_at(-2.5)), "pose": None},
        ],
    )
    succeed_comparison(session, env, first, second)
    current = twin.current(session, env.id)
    by_x = {round(x_of(i), 3): i for i in current}
    # the unverified bowl is added as the first snapshot would have; the unposed one is not
    assert sorted(by_x) == [-1.5, -0.6, 0.1, 0.53, 1.5]
    assert history(session, by_x[0.1].id) == ["inventoried"]  # jitter: no record
    assert history(session, by_x[0.53].id) == ["seeded", "inventoried", "drifted"]
    assert history(session, by_x[1.5].id) == ["inventoried"]
    seen = inventory.last_seen(session, [i.id for i in current])
    assert seen[by_x[0.1].id] == second.id and seen[by_x[0.53].id] == second.id
    assert seen[by_x[-0.6].id] == first.id  # not seen by the second: keeps its state


def test_an_unverified_twin_pose_gives_way_to_a_newer_estimate_a_verified_one_does_not(
    session: Session, env: Environment
) -> None:
    first = snapshot(session, env, 1)
    reconstructed(
        session,
        first,
        [found("bowl", pose_at(0.5, yaw_deg=170.0), verified=False), found("drill", pose_at(0.1))],
    )
    # seq 2 sees both again, unverified, beyond the noise: the bowl's estimate was as unsure
    # as this one and is replaced; the drill's verified pose stands
    second = snapshot(session, env, 2)
    reconstructed(
        session,
        second,
        [
            found("bowl", pose_at(0.5), verified=False),
            found("drill", pose_at(0.1, yaw_deg=20.0), verified=False),
        ],
    )
    succeed_comparison(session, env, first, second)
    by_name = {i.object_name: i for i in twin.current(session, env.id)}
    bowl, drill = by_name["bowl"], by_name["drill"]
    assert history(session, bowl.id) == ["inventoried", "drifted"]
    assert np.allclose(bowl.pose, pose_at(0.5)) and bowl.pose_quality == {
        "verified": False,
        "reasons": [],
    }
    assert history(session, drill.id) == ["inventoried"]
    assert np.allclose(drill.pose, pose_at(0.1))


def test_a_removal_its_own_inventory_contradicts_reopens_the_instance(
    session: Session, env: Environment
) -> None:
    seeded = seed_bowl(session, env, 0.5, "erp:7")
    first = snapshot(session, env, 1)
    reconstructed(session, first, [found("bowl", pose_at(0.5)), found("drill", pose_at(0.1))])
    by_name = {i.object_name: i for i in twin.current(session, env.id)}
    bowl, drill = by_name["bowl"], by_name["drill"]
    assert bowl.id == seeded.id
    # seq 2's comparison removes both (a stretch of shelf the second cloud lacks was named
    # after the bowl); its inventory still shows the bowl where it stood, not the drill
    second = snapshot(session, env, 2)
    reconstructed(session, second, [found("bowl", pose_at(0.503))])
    succeed_comparison(
        session,
        env,
        first,
        second,
        [
            {"type": "removed", "object_name": "bowl", "instance_id": bowl.id},
            {"type": "removed", "object_name": "drill", "instance_id": drill.id},
        ],
    )
    current = twin.current(session, env.id)
    assert [i.id for i in current] == [bowl.id]  # the drill's removal stands
    assert bowl.external_id == "erp:7" and bowl.closed_snapshot_id is None
    assert history(session, bowl.id) == ["inventoried", "removed", "restored"]
    assert x_of(bowl) == 0.5  # 3 mm: the pose estimate's noise, the twin's pose stands
    assert drill.closed_snapshot_id == second.id
    assert inventory.last_seen(session, [bowl.id]) == {bowl.id: second.id}
    event = session.scalars(
        select(Event).where(Event.environment_id == env.id).order_by(Event.created_at.desc())
    ).first()
    assert event is not None and event.data["outcome"] == "applied"
    assert {
        i["instance_id"]: (i["change_type"], i["present"]) for i in event.data["instances"]
    } == {
        bowl.id: ("restored", True),
        drill.id: ("removed", False),
    }


def test_a_pose_the_comparison_just_estimated_gives_way_to_a_verified_one_only(
    session: Session, env: Environment
) -> None:
    first = snapshot(session, env, 1)
    reconstructed(session, first, [found("bowl", pose_at(0.5)), found("drill", pose_at(0.1))])
    by_name = {i.object_name: i for i in twin.current(session, env.id)}
    bowl, drill = by_name["bowl"], by_name["drill"]
    # seq 2's comparison moves both, unverified, the drill turned over; its inventory
    # poses the drill verified and the bowl unverified, each 20° from the comparison's
    second = snapshot(session, env, 2)
    reconstructed(
        session,
        second,
        [found("drill", pose_at(0.3)), found("bowl", pose_at(0.8, yaw_deg=20.0), verified=False)],
    )
    unverified = {"verified": False, "reasons": ["fitness"]}
    succeed_comparison(
        session,
        env,
        first,
        second,
        [
            {
                "type": "moved",
                "object_name": name,
                "instance_id": instance.id,
                "pose": pose_at(x, yaw_deg=yaw),
                "pose_quality": unverified,
            }
            for name, instance, x, yaw in (("drill", drill, 0.3, 170.0), ("bowl", bowl, 0.8, 0.0))
        ],
    )
    assert history(session, drill.id) == ["inventoried", "moved", "drifted"]
    assert np.allclose(drill.pose, pose_at(0.3)) and drill.pose_quality["verified"]
    # two unverified estimates from the same capture: the comparison's stands
    assert history(session, bowl.id) == ["inventoried", "moved"]
    assert np.allclose(bowl.pose, pose_at(0.8))


def test_which_pose_may_replace_which() -> None:
    verified, unverified, pose = {"verified": True}, {"verified": False}, pose_at(0.1)
    assert inventory.takes_inventory_pose(pose, verified, verified)
    assert inventory.takes_inventory_pose(pose, unverified, verified)
    assert inventory.takes_inventory_pose(pose, None, verified)
    assert inventory.takes_inventory_pose(pose, unverified, unverified)
    assert not inventory.takes_inventory_pose(pose, verified, unverified)
    # a pose the twin platform or a person gave has no figures: only a verified one replaces it
    assert not inventory.takes_inventory_pose(pose, None, unverified)
    assert not inventory.takes_inventory_pose(pose, unverified, None)
    # an instance without a pose takes any
    assert inventory.takes_inventory_pose(None, None, unverified)


def test_moved_beyond_noise() -> None:
    assert not inventory.moved_beyond_noise(pose_at(0.1), pose_at(0.105, yaw_deg=2.0))
    assert inventory.moved_beyond_noise(pose_at(0.1), pose_at(0.115))
    assert inventory.moved_beyond_noise(pose_at(0.1), pose_at(0.1, yaw_deg=4.0))
    assert inventory.moved_beyond_noise(None, pose_at(0.1))
    # a can whose model origin is 8 cm off its axis, turned 30° about it: the same object
    turned = pose_at(0.1 - 0.08 * np.cos(np.radians(30)), -0.08 * np.sin(np.radians(30)), 30.0)
    centre = [0.1 - 0.08, 0.0, 0.05]
    assert not inventory.moved_beyond_noise(pose_at(0.1), turned, centre, centre, symmetric=True)
    assert inventory.moved_beyond_noise(pose_at(0.1), turned, centre, centre, symmetric=False)
