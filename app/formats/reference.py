"""The environment's reference: the printed ArUco markers that fix its frame. One reader,
used by the API (``POST /v1/environments``) and the reconstruct stage::

    {"markers": {"dictionary": "DICT_4X4_50",      # optional, this by default
                 "size": 0.15,                      # marker side, metres, 0 < size < 10
                 "poses": {"0": 4×4, "7": 4×4}}}    # env_from_marker by marker id

Marker ids are ASCII digits within the dictionary (``"007"`` is id 7; an id given twice is
refused); poses are rigid (:func:`app.formats.cameras.check_rigid`). Standard library only.
Errors are :class:`FormatError` with code ``InvalidInput``, naming the field.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from app.formats.cameras import Pose, check_rigid
from app.formats.errors import FormatError, show

CODE = "InvalidInput"
DEFAULT_DICTIONARY = "DICT_4X4_50"
ARUCO_DICTIONARIES = {
    f"DICT_{bits}X{bits}_{n}" for bits in (4, 5, 6, 7) for n in (50, 100, 250, 1000)
} | {"DICT_ARUCO_ORIGINAL"}
MAX_SIZE_M = 10.0
# ASCII digits only: "²".isdigit() is True but int("²") fails, and a 5,000-digit id is past
# int()'s limit.
_MARKER_ID = re.compile(r"[0-9]{1,9}")


def dictionary_size(dictionary: str) -> int:
    """How many markers an ArUco dictionary holds: ids are 0..size-1."""
    return 1024 if dictionary == "DICT_ARUCO_ORIGINAL" else int(dictionary.rsplit("_", 1)[1])


@dataclass(frozen=True)
class MarkerSheet:
    """The printed markers: OpenCV ArUco dictionary name, side in metres, and
    ``env_from_marker`` (4×4 rigid, metres) by marker id."""

    dictionary: str
    size_m: float
    env_from_marker: Mapping[int, Pose]

    def to_json(self) -> dict[str, Any]:
        """The normalised reference document (ids as decimal strings)."""
        poses = {str(i): [list(row) for row in m] for i, m in self.env_from_marker.items()}
        return {"markers": {"dictionary": self.dictionary, "size": self.size_m, "poses": poses}}


def read_reference(doc: Any, where: str = "reference") -> MarkerSheet | None:
    """Check a parsed reference document; None for None. :class:`FormatError` naming the
    field (``reference.markers.poses[3]``) when it is not the format above."""
    if doc is None:
        return None
    markers = doc.get("markers") if isinstance(doc, dict) else None
    if not isinstance(markers, dict):
        raise FormatError(where, "expected {'markers': {'dictionary', 'size', 'poses'}}", code=CODE)
    at = f"{where}.markers"
    dictionary = markers.get("dictionary", DEFAULT_DICTIONARY)
    if not isinstance(dictionary, str) or dictionary not in ARUCO_DICTIONARIES:
        raise FormatError(
            f"{at}.dictionary", f"unknown ArUco dictionary {show(dictionary)}", code=CODE
        )
    size = markers.get("size")
    if not isinstance(size, int | float) or isinstance(size, bool) or not 0 < size < MAX_SIZE_M:
        raise FormatError(
            f"{at}.size", f"the marker side in metres, 0 < size < {MAX_SIZE_M:g}", code=CODE
        )
    poses = markers.get("poses")
    if not isinstance(poses, dict) or not poses:
        raise FormatError(f"{at}.poses", "give at least one marker pose", code=CODE)
    return MarkerSheet(dictionary, float(size), _marker_poses(poses, dictionary, f"{at}.poses"))


def _marker_poses(poses: dict[Any, Any], dictionary: str, at: str) -> dict[int, Pose]:
    n_markers = dictionary_size(dictionary)
    checked: dict[int, Pose] = {}
    for marker_id, pose in poses.items():
        if not _MARKER_ID.fullmatch(str(marker_id)):
            raise FormatError(at, f"marker id {show(marker_id)} is not an integer", code=CODE)
        number = int(marker_id)
        if number >= n_markers:
            raise FormatError(
                at, f"marker id {number} is not in {dictionary} (ids 0..{n_markers - 1})", code=CODE
            )
        if number in checked:
            raise FormatError(at, f"marker id {number} is given twice", code=CODE)
        checked[number] = check_rigid(pose, f"{at}[{number}]", code=CODE)
    return checked
