"""The environment's marker reference: the one reader (app/formats/reference.py), shared by
the API and the reconstruct stage."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from app.formats import FormatError
from app.formats.reference import dictionary_size, read_reference
from tests.app.formats.test_cameras import pose


def sheet(**markers: Any) -> dict[str, Any]:
    return {"markers": {"size": 0.15, "poses": {"0": pose()}, **markers}}


def test_a_sheet_reads_normalised_and_round_trips() -> None:
    read = read_reference(sheet(poses={"007": pose(), "3": np.eye(4).tolist()}, size=1))
    assert read is not None
    assert (read.dictionary, read.size_m, list(read.env_from_marker)) == ("DICT_4X4_50", 1.0,
                                                                          [7, 3])  # fmt: skip
    doc = read.to_json()
    assert list(doc["markers"]["poses"]) == ["7", "3"] and doc["markers"]["size"] == 1.0
    assert read_reference(doc) == read
    assert read_reference(None) is None
    assert dictionary_size("DICT_6X6_250") == 250 and dictionary_size("DICT_ARUCO_ORIGINAL") == 1024


@pytest.mark.parametrize(
    ("doc", "field", "problem"),
    [
        ({"marker": {}}, "reference", "expected {'markers'"),
        (sheet(dictionary="DICT_9X9_50"), "reference.markers.dictionary", "unknown ArUco"),
        (sheet(size=0), "reference.markers.size", "0 < size < 10"),
        (sheet(size=True), "reference.markers.size", "0 < size < 10"),
        (sheet(poses={}), "reference.markers.poses", "at least one"),
        (sheet(poses={"²": pose()}), "reference.markers.poses", "'²' is not an integer"),
        (sheet(poses={"9" * 5000: pose()}), "reference.markers.poses", "characters)"),
        (sheet(poses={"50": pose()}), "reference.markers.poses", "ids 0..49"),
        (sheet(poses={"1": pose(), "01": pose()}), "reference.markers.poses", "given twice"),
        (sheet(poses={"2": [[1, 0, 0]]}), "reference.markers.poses[2]", "4×4 matrix"),
        (sheet(poses={"2": (np.eye(4) * 2).tolist()}), "reference.markers.poses[2]",
         "last row"),
    ],
)  # fmt: skip
def test_a_bad_sheet_names_the_field(doc: dict[str, Any], field: str, problem: str) -> None:
    with pytest.raises(FormatError) as err:
        read_reference(doc)
    assert err.value.field == field and problem in err.value.problem, err.value
    assert err.value.code == "InvalidInput"
