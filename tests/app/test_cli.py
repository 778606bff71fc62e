"""The command line's tables."""

from __future__ import annotations

from app.cli import _state_table


def test_the_state_table_shows_seeded_instances_and_their_external_ids() -> None:
    pose = [[1.0, 0, 0, 0.42], [0, 1.0, 0, 1.07], [0, 0, 1.0, 0.8], [0, 0, 0, 1.0]]
    state = {
        "twin": {"snapshot": None, "seq": 0, "status": "current"},
        "objects": [
            {
                "object": "power_drill",
                "pose": pose,
                "since_snapshot": None,  # seeded before any snapshot
                "instance_id": "3f2c",
                "external_id": "urn:plant-7:drill-1",
            },
            {"object": "mug", "pose": None, "since_snapshot": "9c1d", "instance_id": "77aa"},
        ],
    }
    lines = _state_table(state).splitlines()
    assert lines[1].endswith("since snapshot  instance  external id")
    assert lines[2].split() == [
        "power_drill",
        "0.420",
        "1.070",
        "0.800",
        "-",
        "3f2c",
        "urn:plant-7:drill-1",
    ]
    assert lines[3].split() == ["mug", "-", "-", "-", "9c1d", "77aa", "-"]
