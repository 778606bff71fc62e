"""Seeding and correcting the twin by hand (:mod:`app.core.seeding`): instances with the
platform's ``external_id``, all-or-nothing imports that name the bad row, where the seeded
records stand in the twin's seq order, and seeded instances closed and moved by the twin's
own apply path like any other."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from sqlalchemy import func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from app.core import seeding, twin
from app.core.enums import ChangeType
from app.core.errors import Conflict, InvalidInput, NotFound
from app.core.models import Environment, InstancePose, LibraryObject, TwinInstance
from tests.app.core.test_twin import Chain, apply, chain, change, pose_at

__all__ = ["chain"]  # the fixture, imported for these tests


def rotated(seed: int, x_m: float = 0.0) -> list[list[float]]:
    pose = np.eye(4)
    pose[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    pose[:3, 3] = [x_m, 0.2, 0.0]
    return [[float(v) for v in row] for row in pose]


def reflect_baseline(session: Session, chain: Chain) -> None:
    """The twin reflects snapshot seq 1 (its baseline), as the chain leaves it."""
    env = session.get(Environment, chain.env_id)
    assert env is not None
    env.twin_seq, env.twin_snapshot_id = 1, chain.snapshot_ids[0]
    session.flush()


def count(session: Session, env_id: str) -> tuple[int, int]:
    instances = session.scalar(
        select(func.count()).select_from(TwinInstance).where(TwinInstance.environment_id == env_id)
    )
    records = session.scalar(
        select(func.count())
        .select_from(InstancePose)
        .join(TwinInstance)
        .where(TwinInstance.environment_id == env_id)
    )
    return int(instances or 0), int(records or 0)


def test_a_seed_before_any_snapshot_stands_from_the_start(session: Session, chain: Chain) -> None:
    (drill,) = seeding.seed(
        session, chain.env_id, [seeding.Seed("drill", pose_at(0.2), "urn:cell7:drill-1")]
    )
    assert drill.external_id == "urn:cell7:drill-1"
    assert (drill.created_snapshot_id, drill.since_snapshot_id) == (None, None)
    assert [i.id for i in twin.current(session, chain.env_id)] == [drill.id]
    # state_at counts it at every seq: the first comparison's "before" holds it
    for seq in (1, 2, 3):
        assert [(i.id, r.change_type) for i, r in twin.state_at(session, chain.env_id, seq)] == [
            (drill.id, "seeded")
        ]
    _, poses = twin.history(session, chain.env_id, drill.id)
    assert [(p.change_type, p.snapshot_id, p.pose) for p in poses] == [
        ("seeded", None, pose_at(0.2))
    ]


def test_seeded_instances_are_closed_and_moved_by_the_comparisons_that_follow(
    session: Session, chain: Chain
) -> None:
    reflect_baseline(session, chain)
    drill, bowl = seeding.seed(
        session,
        chain.env_id,
        [
            seeding.Seed("drill", pose_at(0.1), "plc-drill"),
            seeding.Seed("bowl", pose_at(0.5), "plc-bowl"),
        ],
    )
    snap1, snap2, snap3 = chain.snapshot_ids
    assert drill.created_snapshot_id == snap1  # the snapshot the twin reflects
    # what the comparison 1→2 reads as its "before" twin
    assert {i.external_id for i, _ in twin.state_at(session, chain.env_id, 1)} == {
        "plc-drill",
        "plc-bowl",
    }
    apply(session, chain, 2, [change(ChangeType.removed, "bowl", bowl.id)])
    apply(session, chain, 3, [change(ChangeType.moved, "drill", drill.id, pose=pose_at(0.3))])

    assert [(i.id, i.external_id, i.pose) for i in twin.current(session, chain.env_id)] == [
        (drill.id, "plc-drill", pose_at(0.3))
    ]
    assert bowl.closed_snapshot_id == snap2
    _, drill_poses = twin.history(session, chain.env_id, drill.id)
    assert [(p.change_type, p.snapshot_id) for p in drill_poses] == [
        ("seeded", snap1),
        ("moved", snap3),
    ]
    assert [i.id for i, _ in twin.state_at(session, chain.env_id, 2)] == [drill.id]
    # the bowl's external id is free again once it is closed
    (again,) = seeding.seed(session, chain.env_id, [seeding.Seed("bowl", pose_at(0.9), "plc-bowl")])
    assert again.external_id == "plc-bowl"


def ten_rows() -> list[seeding.Seed]:
    return [seeding.Seed("mug", pose_at(0.1 * i), f"mug-{i}") for i in range(10)]


BAD_ROWS: list[tuple[seeding.Seed, str]] = [
    (seeding.Seed("hammer", pose_at(0.7), "x"), "unknown class 'hammer'"),
    (
        seeding.Seed("mug", [[1.1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "x"),
        "not orthonormal",
    ),
    (
        seeding.Seed("mug", [[-1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "x"),
        "determinant -1",
    ),
    (
        seeding.Seed("mug", [[math.nan, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "x"),
        "finite numbers",
    ),
    (seeding.Seed("mug", [[1.0, 0, 0], [0, 1, 0], [0, 0, 1]], "x"), "4×4"),
    (
        seeding.Seed("mug", [[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]], "x"),
        "last row",
    ),
    (seeding.Seed("mug", pose_at(0.7), "mug-2"), "external_id 'mug-2' repeats row 2"),
    (seeding.Seed("mug", pose_at(0.7), " padded"), "surrounding whitespace"),
    (seeding.Seed("mug", pose_at(0.7), "x" * 201), "longer than 200"),
]


@pytest.mark.parametrize(("bad", "problem"), BAD_ROWS, ids=[p for _, p in BAD_ROWS])
def test_a_bad_row_7_of_10_is_named_and_nothing_is_written(
    session: Session, chain: Chain, bad: seeding.Seed, problem: str
) -> None:
    seeding.seed(session, chain.env_id, [seeding.Seed("drill", pose_at(0.0), "held")])
    before = count(session, chain.env_id)
    rows = ten_rows()
    rows[7] = bad
    with pytest.raises(InvalidInput) as err:
        seeding.seed(session, chain.env_id, rows)
    assert err.value.status_code == 422
    assert err.value.detail.startswith("1 of 10 rows refused, nothing was written: row 7: ")
    assert problem in err.value.detail
    assert count(session, chain.env_id) == before


def test_an_external_id_an_open_instance_holds_is_refused_and_every_bad_row_named(
    session: Session, chain: Chain
) -> None:
    (held,) = seeding.seed(session, chain.env_id, [seeding.Seed("drill", pose_at(0), "A-1")])
    rows = [
        seeding.Seed("mug", pose_at(0.1), "A-1"),
        seeding.Seed("mug", pose_at(0.2), "A-2"),
        seeding.Seed("vase", pose_at(0.3), None),
    ]
    with pytest.raises(InvalidInput) as err:
        seeding.seed(session, chain.env_id, rows)
    assert f"row 0: external_id 'A-1' is held by open instance {held.id}" in err.value.detail
    assert "row 2: unknown class 'vase'" in err.value.detail
    assert "row 1" not in err.value.detail
    assert err.value.detail.startswith("2 of 3 rows refused")
    with pytest.raises(InvalidInput, match=r"^nothing was written: unknown class 'vase'"):
        seeding.seed(session, chain.env_id, rows[2:], one=True)


def test_a_class_by_library_object_id_and_poses_made_exactly_rigid(
    session: Session, chain: Chain
) -> None:
    mug = LibraryObject(name="mug", filename="m.ply", file_key="k", size_bytes=1)
    session.add(mug)
    session.flush()
    pose = np.asarray(rotated(3, 0.4))
    pose[:3, :3] += 2e-4 * np.random.default_rng(0).standard_normal((3, 3))  # rounding
    (by_id, by_name) = seeding.seed(
        session,
        chain.env_id,
        [seeding.Seed(mug.id, pose.tolist()), seeding.Seed("mug", rotated(4))],
    )
    assert (by_id.object_name, by_id.object_id) == ("mug", mug.id)
    assert (by_name.object_name, by_name.object_id) == ("mug", mug.id)
    assert by_id.external_id is None
    stored = np.asarray(by_id.pose)
    r = stored[:3, :3]
    assert np.abs(r @ r.T - np.eye(3)).max() < 1e-12
    assert np.abs(stored - pose).max() < 1e-3  # the nearest rotation: a rounding's worth
    assert stored[:3, 3].tolist() == pose[:3, 3].tolist()


def test_a_correction_sets_pose_class_and_external_id_on_the_record(
    session: Session, chain: Chain
) -> None:
    reflect_baseline(session, chain)
    drill, mug = seeding.seed(
        session,
        chain.env_id,
        [seeding.Seed("drill", pose_at(0.1), "D"), seeding.Seed("mug", pose_at(0.5), "M")],
    )
    seeding.correct(session, chain.env_id, drill.id, pose=pose_at(0.15), external_id="D-2")
    assert (drill.pose, drill.external_id) == (pose_at(0.15), "D-2")
    seeding.correct(session, chain.env_id, mug.id, object_class="bowl", external_id=None)
    assert (mug.object_name, mug.external_id) == ("bowl", None)
    _, poses = twin.history(session, chain.env_id, drill.id)
    assert [(p.change_type, p.pose) for p in poses] == [
        ("seeded", pose_at(0.1)),
        ("corrected", pose_at(0.15)),
    ]
    # the corrected pose is the twin as of the snapshot it reflects
    state = {i.id: r.pose for i, r in twin.state_at(session, chain.env_id, 1)}
    assert state[drill.id] == pose_at(0.15)

    with pytest.raises(InvalidInput, match="held by open instance"):
        seeding.seed(session, chain.env_id, [seeding.Seed("mug", pose_at(1), "D-2")])
    seeding.seed(session, chain.env_id, [seeding.Seed("mug", pose_at(1), "M")])  # freed
    with pytest.raises(InvalidInput, match=f"is held by open instance {drill.id}"):
        seeding.correct(session, chain.env_id, mug.id, external_id="D-2")
    with pytest.raises(InvalidInput, match="unknown class 'saw'"):
        seeding.correct(session, chain.env_id, mug.id, object_class="saw")
    with pytest.raises(InvalidInput, match="not orthonormal"):
        seeding.correct(
            session,
            chain.env_id,
            mug.id,
            object_class="drill",
            pose=[[2.0, 0, 0, 0], *pose_at(0)[1:]],
        )
    assert (mug.object_name, mug.pose) == ("bowl", pose_at(0.5))  # refused: all unchanged
    with pytest.raises(NotFound):
        seeding.correct(session, "nope", drill.id, external_id="x")


def test_retiring_closes_at_the_reflected_snapshot_or_deletes_a_seed_never_applied(
    session: Session, chain: Chain
) -> None:
    (early,) = seeding.seed(session, chain.env_id, [seeding.Seed("drill", pose_at(0), "E")])
    assert seeding.retire(session, chain.env_id, early.id) is None
    assert count(session, chain.env_id) == (0, 0)

    reflect_baseline(session, chain)
    (late,) = seeding.seed(session, chain.env_id, [seeding.Seed("drill", pose_at(0), "E")])
    retired = seeding.retire(session, chain.env_id, late.id)
    assert retired is not None and retired.closed_snapshot_id == chain.snapshot_ids[0]
    assert twin.current(session, chain.env_id) == []
    _, poses = twin.history(session, chain.env_id, late.id)
    assert [p.change_type for p in poses] == ["seeded", "retired"]
    with pytest.raises(Conflict) as err:
        seeding.retire(session, chain.env_id, late.id)
    assert err.value.code == "InstanceClosed"
    with pytest.raises(Conflict):
        seeding.correct(session, chain.env_id, late.id, pose=pose_at(1))


@pytest.mark.parametrize(
    ("value", "problem"),
    [
        ("not a matrix", "4×4"),
        ([[1, 0, 0, 0]] * 4, "not orthonormal"),
        ([[True, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "finite numbers"),
        ([[1, 0, 0, math.inf], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "finite numbers"),
    ],
)
def test_check_pose_names_the_problem(value: Any, problem: str) -> None:
    with pytest.raises(ValueError, match=problem):
        seeding.check_pose(value)


def test_the_database_holds_one_open_instance_per_external_id(
    session: Session, chain: Chain
) -> None:
    """The partial unique index behind the checks above (PostgreSQL and SQLite)."""

    def add(external_id: str | None, closed: str | None = None) -> None:
        session.add(
            TwinInstance(
                environment_id=chain.env_id,
                object_name="drill",
                external_id=external_id,
                closed_snapshot_id=closed,
            )
        )
        session.flush()

    add("X", closed=chain.snapshot_ids[0])
    add("X")  # a closed one does not count
    add(None)
    add(None)  # nor does having none
    with pytest.raises(IntegrityError), session.begin_nested():
        add("X")


def test_a_move_of_an_instance_retired_meanwhile_adds_it_anew(
    session: Session, chain: Chain
) -> None:
    """A comparison that read the instance open, applied after it was retired by hand."""
    reflect_baseline(session, chain)
    (drill,) = seeding.seed(session, chain.env_id, [seeding.Seed("drill", pose_at(0.1), "D")])
    seeding.retire(session, chain.env_id, drill.id)
    apply(session, chain, 2, [change(ChangeType.moved, "drill", drill.id, pose=pose_at(0.3))])
    [now] = twin.current(session, chain.env_id)
    assert now.id != drill.id and (now.pose, now.external_id) == (pose_at(0.3), None)
    _, poses = twin.history(session, chain.env_id, drill.id)
    assert [p.change_type for p in poses] == ["seeded", "retired"]
