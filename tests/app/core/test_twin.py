"""The twin's instance records, directly: :func:`app.core.twin.apply_changes` writes a
comparison's changes (added, removed, moved, swapped, unidentified) into instances and their
pose history; :func:`current`, :func:`history` and :func:`state_at` read them back. The chain
that decides when changes are applied is tested in ``test_twin_order.py``."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from itertools import pairwise
from typing import Any

import pytest
from sqlalchemy.orm import Session

from app.core import twin
from app.core.enums import ChangeType, JobKind, SnapshotState
from app.core.errors import NotFound
from app.core.models import (
    Comparison,
    Environment,
    InstancePose,
    Job,
    LibraryObject,
    Snapshot,
    TwinInstance,
    new_id,
)


def pose_at(x_m: float) -> list[list[float]]:
    """A 4×4 env_from_object pose translated by ``x_m`` metres along x."""
    return [[1.0, 0, 0, x_m], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]]


@dataclass(frozen=True)
class Chain:
    """An environment with reconstructed snapshots of seq 1..3 and the automatic comparisons
    1→2 and 2→3 (their jobs are rows only: nothing is queued)."""

    env_id: str
    snapshot_ids: list[str]  # index i is seq i + 1
    comparison_ids: list[str]  # [1→2, 2→3]
    drill_object_id: str


@pytest.fixture
def chain(session: Session) -> Chain:
    env = Environment(name=f"env-{new_id()[:8]}", classes=["drill", "bowl", "mug"])
    drill = LibraryObject(
        name=f"drill-{new_id()[:8]}", filename="d.ply", file_key="k", size_bytes=1
    )
    session.add_all([env, drill])
    session.flush()
    snaps = [
        Snapshot(
            environment_id=env.id,
            seq=seq,
            storage_prefix=f"p/{seq}",
            state=SnapshotState.reconstructed,
        )
        for seq in (1, 2, 3)
    ]
    session.add_all(snaps)
    session.flush()
    comparison_ids = []
    for before, after in pairwise(snaps):
        comparison_id = new_id()
        job = Job(
            kind=JobKind.comparison,
            task_name="comparison.run",
            environment_id=env.id,
            comparison_id=comparison_id,
        )
        session.add(job)
        session.flush()
        session.add(
            Comparison(
                id=comparison_id,
                environment_id=env.id,
                before_id=before.id,
                after_id=after.id,
                job_id=job.id,
                automatic=True,
            )
        )
        comparison_ids.append(comparison_id)
    session.flush()
    return Chain(env.id, [s.id for s in snaps], comparison_ids, drill.id)


def change(
    kind: ChangeType, obj: str | None, instance_id: str | None, **more: Any
) -> dict[str, Any]:
    return {"type": kind, "object": obj, "instance_id": instance_id, **more}


def apply(session: Session, chain: Chain, seq: int, changes: list[dict[str, Any]]) -> None:
    """Apply ``changes`` as those of the automatic comparison that ends at snapshot ``seq``."""
    twin.apply_changes(
        session,
        chain.env_id,
        chain.snapshot_ids[seq - 1],
        chain.comparison_ids[seq - 2],
        changes,
        {"drill": chain.drill_object_id},
    )


def first_two_snapshots(session: Session, chain: Chain) -> tuple[str, str, str]:
    """Seq 2 adds a drill at x = 0.1 m and a bowl at x = 0.5 m; seq 3 moves the drill to
    x = 0.3 m and swaps the bowl for a mug at x = 0.6 m. Returns the three instance ids."""
    drill, bowl, mug = new_id(), new_id(), new_id()
    apply(
        session,
        chain,
        2,
        [
            change(ChangeType.added, "drill", drill, pose=pose_at(0.1), centroid_env=[0.1, 0, 0]),
            change(ChangeType.added, "bowl", bowl, pose=pose_at(0.5), pose_quality={"ok": 1}),
        ],
    )
    apply(
        session,
        chain,
        3,
        [
            change(ChangeType.moved, "drill", drill, pose=pose_at(0.3), centroid_env=[0.3, 0, 0]),
            change(ChangeType.swapped, "mug", mug, pose=pose_at(0.6), replaced_instance_id=bowl),
        ],
    )
    return drill, bowl, mug


def test_added_instances_are_current_with_their_pose_object_and_history(
    session: Session, chain: Chain
) -> None:
    drill, bowl = new_id(), new_id()
    apply(
        session,
        chain,
        2,
        [
            change(ChangeType.added, "drill", drill, pose=pose_at(0.1), centroid_env=[0.1, 0, 0]),
            change(ChangeType.added, "bowl", bowl, pose=None),
        ],
    )
    current = twin.current(session, chain.env_id)
    assert [i.id for i in current] == [drill, bowl]
    assert current[0].pose == pose_at(0.1) and current[0].centroid_env == [0.1, 0, 0]
    assert current[0].object_id == chain.drill_object_id  # from the object_ids map
    assert current[1].object_id is None and current[1].pose is None  # not in the map
    snap2 = chain.snapshot_ids[1]
    assert {i.created_snapshot_id for i in current} == {snap2}
    assert {i.since_snapshot_id for i in current} == {snap2}
    instance, poses = twin.history(session, chain.env_id, drill)
    assert instance.id == drill
    assert [(p.change_type, p.pose, p.snapshot_id) for p in poses] == [
        ("added", pose_at(0.1), snap2)
    ]
    assert poses[0].comparison_id == chain.comparison_ids[0]


def test_moved_updates_the_pose_and_swapped_closes_one_and_opens_another(
    session: Session, chain: Chain
) -> None:
    drill, bowl, mug = first_two_snapshots(session, chain)
    snap2, snap3 = chain.snapshot_ids[1], chain.snapshot_ids[2]
    current = twin.current(session, chain.env_id)
    assert [i.id for i in current] == [drill, mug]
    moved = current[0]
    assert moved.pose == pose_at(0.3) and moved.centroid_env == [0.3, 0, 0]
    assert moved.since_snapshot_id == snap3 and moved.created_snapshot_id == snap2
    _, drill_poses = twin.history(session, chain.env_id, drill)
    assert [(p.change_type, p.pose) for p in drill_poses] == [
        ("added", pose_at(0.1)),
        ("moved", pose_at(0.3)),
    ]
    closed, bowl_poses = twin.history(session, chain.env_id, bowl)
    assert closed.closed_snapshot_id == snap3 and closed.closed_at is not None
    assert [(p.change_type, p.pose) for p in bowl_poses] == [
        ("added", pose_at(0.5)),
        ("swapped", None),
    ]
    _, mug_poses = twin.history(session, chain.env_id, mug)
    assert [(p.change_type, p.pose, p.snapshot_id) for p in mug_poses] == [
        ("swapped", pose_at(0.6), snap3)
    ]


def test_removed_closes_the_instance(session: Session, chain: Chain) -> None:
    drill = new_id()
    apply(session, chain, 2, [change(ChangeType.added, "drill", drill, pose=pose_at(0.1))])
    apply(session, chain, 3, [change(ChangeType.removed, "drill", drill)])
    assert twin.current(session, chain.env_id) == []
    instance, poses = twin.history(session, chain.env_id, drill)
    assert instance.closed_snapshot_id == chain.snapshot_ids[2]
    assert [(p.change_type, p.pose) for p in poses] == [("added", pose_at(0.1)), ("removed", None)]


def test_state_at_is_the_twin_as_it_stood_after_each_snapshot(
    session: Session, chain: Chain
) -> None:
    drill, bowl, mug = first_two_snapshots(session, chain)

    def at(seq: int) -> list[tuple[str, str, list[list[float]] | None]]:
        return [
            (instance.id, record.change_type, record.pose)
            for instance, record in twin.state_at(session, chain.env_id, seq)
        ]

    assert at(1) == []
    assert at(2) == [(drill, "added", pose_at(0.1)), (bowl, "added", pose_at(0.5))]
    assert at(3) == [(drill, "moved", pose_at(0.3)), (mug, "swapped", pose_at(0.6))]
    assert at(99) == at(3)


def test_a_moved_instance_that_is_not_open_is_added(session: Session, chain: Chain) -> None:
    """A move of an instance the twin does not hold (closed, or never seen) creates it."""
    ghost = new_id()
    apply(session, chain, 2, [change(ChangeType.moved, "drill", ghost, pose=pose_at(0.2))])
    [instance] = twin.current(session, chain.env_id)
    assert instance.id == ghost and instance.pose == pose_at(0.2)
    _, poses = twin.history(session, chain.env_id, ghost)
    assert [p.change_type for p in poses] == ["added"]


def test_unidentified_changes_and_unknown_instances_leave_the_twin_alone(
    session: Session, chain: Chain, caplog: pytest.LogCaptureFixture
) -> None:
    drill = new_id()
    apply(session, chain, 2, [change(ChangeType.added, "drill", drill, pose=pose_at(0.1))])
    caplog.set_level(logging.WARNING, logger="app.core.twin")
    apply(
        session,
        chain,
        3,
        [
            change(ChangeType.unidentified, None, None, pose=pose_at(0.9)),
            change(ChangeType.removed, "bowl", new_id()),  # no such instance
            change(ChangeType.removed, "bowl", None),
        ],
    )
    assert [i.id for i in twin.current(session, chain.env_id)] == [drill]
    assert session.query(InstancePose).count() == 1
    assert session.query(TwinInstance).count() == 1
    assert caplog.text.count("names no open instance") == 2


def test_history_of_an_instance_elsewhere_is_not_found(session: Session, chain: Chain) -> None:
    drill = new_id()
    apply(session, chain, 2, [change(ChangeType.added, "drill", drill)])
    other = Environment(name=f"env-{new_id()[:8]}", classes=["drill"])
    session.add(other)
    session.flush()
    with pytest.raises(NotFound):
        twin.history(session, other.id, drill)
    with pytest.raises(NotFound):
        twin.history(session, chain.env_id, new_id())
