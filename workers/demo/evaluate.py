"""Score a comparison against a generated scene's ground truth: every true change matched by
(type, object), false changes counted, pose errors symmetry-aware (the minimum over the
object's symmetry group, as BOP's MSSD/ADD-S do)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from workers.pipeline.geometry import pose_error
from workers.pipeline.pose import symmetric_pose_error
from workers.pipeline.symmetry import spec_from_json


@dataclass(frozen=True)
class Match:
    truth: dict[str, Any]
    found: dict[str, Any] | None
    translation_error_m: float | None
    rotation_error_deg: float | None
    xyz_error_m: list[float] | None
    rpy_error_deg: list[float] | None


def roll_pitch_yaw_deg(rotation: np.ndarray) -> list[float]:
    """ZYX Euler angles (roll about x, pitch about y, yaw about z) of a 3×3 rotation, degrees."""
    r = rotation
    pitch = math.asin(max(-1.0, min(1.0, -r[2, 0])))
    roll = math.atan2(r[2, 1], r[2, 2])
    yaw = math.atan2(r[1, 0], r[0, 0])
    return [math.degrees(a) for a in (roll, pitch, yaw)]


def _symmetry(truth: dict[str, Any], name: str) -> Any:
    raw = (truth.get("objects", {}).get(name) or {}).get("symmetry")
    if not raw:
        return None
    raw = dict(raw)
    if "point" in raw and "origin" not in raw:
        raw["origin"] = raw.pop("point")
    return spec_from_json(raw)


def errors(
    estimated: Any, true: Any, symmetry: Any
) -> tuple[float, float, list[float], list[float]]:
    """(translation m, geodesic rotation deg, per-axis xyz m, roll/pitch/yaw deg of the
    residual rotation), minimised over ``symmetry`` when given."""
    est, tru = np.asarray(estimated, dtype=np.float64), np.asarray(true, dtype=np.float64)
    if symmetry is not None and symmetry.kind != "none":
        dt, dr = symmetric_pose_error(est, tru, symmetry)
    else:
        dt, dr = pose_error(est, tru)
    xyz = (est[:3, 3] - tru[:3, 3]).tolist()
    residual = tru[:3, :3].T @ est[:3, :3]
    rpy = (
        roll_pitch_yaw_deg(residual)
        if symmetry is None or symmetry.kind == "none"
        else [float("nan")] * 3
    )
    return dt, dr, xyz, rpy


def match_changes(
    truth: dict[str, Any], found: list[dict[str, Any]]
) -> tuple[list[Match], list[dict[str, Any]]]:
    """Pair every true change with a found one of the same type and object; returns the
    matches (``found`` None when missed) and the found changes no truth explains."""
    unused = list(found)
    matches: list[Match] = []
    for change in truth["changes"]:
        candidates = [
            f for f in unused if f["type"] == change["type"] and f.get("object") == change["object"]
        ]
        if not candidates:
            matches.append(Match(change, None, None, None, None, None))
            continue
        chosen = candidates[0]
        unused.remove(chosen)
        dt = dr = None
        xyz = rpy = None
        if change.get("pose") is not None and chosen.get("pose") is not None:
            dt, dr, xyz, rpy = errors(
                chosen["pose"], change["pose"], _symmetry(truth, change["object"])
            )
        matches.append(Match(change, chosen, dt, dr, xyz, rpy))
    return matches, unused
