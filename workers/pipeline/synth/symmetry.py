"""Symmetry-aware pose errors against the ground truth.

A ``symmetry`` spec (object frame, as in ground_truth.json) is None, or
``{"kind": "continuous", "axis": [x, y, z], "point": [x, y, z]}`` (any rotation about that
axis leaves the shape unchanged), or ``{"kind": "discrete", "transforms": [4×4, ...]}``
(``object_from_object`` maps that leave it unchanged; the identity is implied).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from workers.pipeline.errors import InputError
from workers.pipeline.geometry import Mat4, as_mat4, make_rigid, pose_error


def _axis_rotation(axis: NDArray[np.float64], angle_rad: float) -> NDArray[np.float64]:
    """(3, 3) rotation by ``angle_rad`` about the unit ``axis`` (Rodrigues)."""
    k = np.asarray([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    out: NDArray[np.float64] = np.eye(3) + np.sin(angle_rad) * k + (1 - np.cos(angle_rad)) * (k @ k)
    return out


def equivalent_transforms(symmetry: dict[str, Any] | None, steps: int = 720) -> list[Mat4]:
    """``object_from_object`` maps that leave the shape unchanged (identity first);
    a continuous symmetry is sampled every 360°/``steps``."""
    if symmetry is None:
        return [np.eye(4)]
    if symmetry.get("kind") == "discrete":
        return [np.eye(4)] + [as_mat4(t, "symmetry transform") for t in symmetry["transforms"]]
    if symmetry.get("kind") != "continuous":
        raise InputError(f"unknown symmetry kind in {symmetry!r}")
    axis = np.asarray(symmetry["axis"], np.float64)
    axis = axis / np.linalg.norm(axis)
    point = np.asarray(symmetry.get("point", [0.0, 0.0, 0.0]), np.float64)
    out = []
    for angle in np.linspace(0.0, 2.0 * np.pi, steps, endpoint=False):
        rot = _axis_rotation(axis, float(angle))
        out.append(make_rigid(rot, point - rot @ point))
    return out


def symmetric_pose_error(
    estimated_env_from_object: ArrayLike,
    true_env_from_object: ArrayLike,
    symmetry: dict[str, Any] | None,
) -> tuple[float, float]:
    """(translation m, rotation deg): the smallest :func:`pose_error` between the estimate
    and the true pose composed with any symmetry of the object (0.25° resolution for a
    continuous symmetry)."""
    estimated = as_mat4(estimated_env_from_object, "estimated_env_from_object")
    true = as_mat4(true_env_from_object, "true_env_from_object")
    errors = [pose_error(estimated, true @ s) for s in equivalent_transforms(symmetry)]
    return min(errors, key=lambda e: (e[1], e[0]))
