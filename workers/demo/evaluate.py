"""Score a comparison against a generated scene's ground truth: every true change matched by
(type, object), false changes counted, pose errors symmetry-aware (the minimum over the
object's symmetry group, as BOP's MSSD/ADD-S do)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from workers.pipeline.geometry import pose_error
from workers.pipeline.model.symmetry_group import spec_from_json, symmetric_pose_error


@dataclass(frozen=True)
class Match:
    """A true change and the found change paired with it (None when missed); the pose errors
    (see :class:`PoseErrors`) are None unless both carry a pose."""

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
    return spec_from_json(raw) if raw else None


@dataclass(frozen=True)
class PoseErrors:
    """How far an estimated env_from_object pose is from the true one: translation (m) and
    geodesic rotation (degrees), minimised over the object's symmetry when it has one; the
    per-axis translation (x, y, z, m) and the residual rotation as roll/pitch/yaw (degrees;
    NaN for a symmetric object, where no single residual is meaningful)."""

    translation_m: float
    rotation_deg: float
    xyz_m: list[float]
    rpy_deg: list[float]


def errors(estimated: Any, true: Any, symmetry: Any) -> PoseErrors:
    """The :class:`PoseErrors` of 4×4 ``estimated`` against 4×4 ``true`` (metres),
    minimised over ``symmetry`` when given."""
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
    return PoseErrors(dt, dr, xyz, rpy)


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
        if change.get("pose") is None or chosen.get("pose") is None:
            matches.append(Match(change, chosen, None, None, None, None))
            continue
        e = errors(chosen["pose"], change["pose"], _symmetry(truth, change["object"]))
        matches.append(Match(change, chosen, e.translation_m, e.rotation_deg, e.xyz_m, e.rpy_deg))
    return matches, unused
