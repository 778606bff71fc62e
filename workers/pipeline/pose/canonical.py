"""Step 5 of pose estimation: one canonical pose among a symmetric object's equivalents.

Among the equivalent poses ``env_from_object @ S`` one is published: the one whose model
colours match the scene's clearly best when colour breaks a discrete symmetry (a label;
among those standing the same way up), or, for a round object that flips end over end (a
can), on the end its colours hold; else the one closest to a previous pose if given, else
the one whose object up axis agrees best with the environment up, ties broken by the
smallest rotation, so a symmetric object is never published upside down only because the
fit is equally good.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from workers.pipeline.geometry import Mat4, rotation_angle_deg, transform_points
from workers.pipeline.model import PreparedModel
from workers.pipeline.model.symmetry_group import SymmetrySpec
from workers.pipeline.pose.fit import Target

#: equivalents whose object up is tilted from the environment's up at most this much more
#: than the least tilted one's count as standing the same way up (an angle: a window in
#: cosines would be narrow at the horizontal, where a lying object's equivalents all are)
UP_WINDOW_DEG = 11.5


def _same_way_up(ups: NDArray[np.float64]) -> NDArray[np.bool_]:
    """(N,) which of (N,) cosines between object up and environment up stand as the least
    tilted does, within :data:`UP_WINDOW_DEG`."""
    tilt = np.degrees(np.arccos(np.clip(ups, -1.0, 1.0)))
    same: NDArray[np.bool_] = tilt <= tilt.min() + UP_WINDOW_DEG
    return same


#: turns about a round object's axis, degrees, over which its colour is tried per end
SPIN_STEP_DEG = 10.0


def _way_up_by_colour(
    env_from_object: Mat4,
    symmetry: SymmetrySpec,
    colour: Callable[[Mat4], float],
    margin: float,
) -> int | None:
    """Which of a round object's discrete elements (which end up: a can's label reads one
    way) its colours hold: the index of the element whose best ``colour`` over turns about
    the axis (every :data:`SPIN_STEP_DEG`) beats every other element's by ``margin``; None
    when none does or colour is unknown."""
    best = []
    for element in symmetry.rotations:
        scores = np.array(
            [
                colour(env_from_object @ symmetry.continuous_rotation(a) @ element)
                for a in np.radians(np.arange(0.0, 360.0, SPIN_STEP_DEG))
            ]
        )
        if not np.isfinite(scores).any():
            return None
        best.append(float(np.nanmax(scores)))
    order = np.argsort(best)[::-1]
    return int(order[0]) if best[order[0]] - best[order[1]] >= margin else None


@dataclass(frozen=True)
class CanonicalPose:
    """The published ``env_from_object``, why (``chosen_by``: "unique", "colour",
    "previous" or "up"), the ``equivalents`` (other poses equal by symmetry; continuous
    symmetry: 8 samples per discrete element), and for continuous symmetry its
    ``axis_env`` (unit (3,)) through ``origin_env`` ((3,), metres), else None."""

    env_from_object: Mat4
    chosen_by: str
    equivalents: tuple[Mat4, ...]
    axis_env: NDArray[np.float64] | None = None
    origin_env: NDArray[np.float64] | None = None


def colour_agreement(
    model: PreparedModel, env_from_object: Mat4, target: Target, dist: float
) -> float:
    """Correlation of the model's colours with the colours of the nearest scene points
    within ``dist`` metres, each side's mean removed per face direction (the posed model
    normal's nearest of ±x, ±y, ±z: light shades each face by its direction, the texture
    varies within it); NaN without colours or with < 100 pairs."""
    if model.colors is None or target.colors is None:
        return float("nan")
    d, idx = target.tree.query(
        transform_points(env_from_object, model.points), distance_upper_bound=dist
    )
    ok = np.isfinite(d)
    if ok.sum() < 100:
        return float("nan")
    a, b = model.colors[ok].copy(), target.colors[idx[ok]].copy()
    normals = model.normals[ok] @ env_from_object[:3, :3].T
    axis = np.argmax(np.abs(normals), axis=1)
    face = 2 * axis + (normals[np.arange(len(axis)), axis] > 0)
    for f in np.unique(face):
        mine = face == f
        a[mine] -= a[mine].mean(axis=0)
        b[mine] -= b[mine].mean(axis=0)
    den = float(np.sqrt((a * a).sum() * (b * b).sum()))
    return float((a * b).sum() / den) if den > 0 else float("nan")


def _choose_equivalent(
    env_from_object: Mat4,
    symmetry: SymmetrySpec,
    up_object: NDArray[np.float64],
    up_env: NDArray[np.float64],
    previous: Mat4 | None,
    colour: Callable[[Mat4], float] | None = None,
    colour_margin: float = 0.1,
) -> CanonicalPose:
    """Pick one pose among ``env_from_object @ S`` (without the continuous axis).

    Order: ``colour`` (a discrete group whose colours break it: among the elements that
    stand the same way up as the least tilted (:func:`_same_way_up`) — never upside down;
    every side of a lying box — the one whose colour agreement beats the others by
    ``colour_margin``; a round object with more than one discrete element: the end up
    that :func:`_way_up_by_colour` names, the turn about the axis then as below), then
    ``previous``, then ``up``."""
    if not symmetry.is_symmetric:
        return CanonicalPose(env_from_object, "unique", ())
    if colour is not None and symmetry.kind == "discrete" and symmetry.appearance_breaks:
        poses = [env_from_object @ s for s in symmetry.rotations]
        ups = np.array([p[:3, :3] @ up_object @ up_env for p in poses])
        upright = [p for p, same in zip(poses, _same_way_up(ups), strict=True) if same]
        scores = np.array([colour(p) for p in upright])
        if len(upright) > 1 and np.isfinite(scores).all():
            order = np.argsort(-scores)
            if scores[order[0]] - scores[order[1]] >= colour_margin:
                chosen = upright[int(order[0])]
                return CanonicalPose(
                    chosen, "colour", tuple(chosen @ s for s in symmetry.rotations[1:])
                )
    side = None
    if symmetry.kind == "continuous":
        elements = symmetry.rotations
        if colour is not None and symmetry.appearance_breaks and len(elements) > 1:
            side = _way_up_by_colour(env_from_object, symmetry, colour, colour_margin)
            elements = elements if side is None else (elements[side],)
        grid = [
            env_from_object @ symmetry.continuous_rotation(a) @ s
            for s in elements
            for a in np.radians(np.arange(0.0, 360.0, 0.5))
        ]
    else:
        grid = [env_from_object @ s for s in symmetry.rotations]
    rots = np.stack([g[:3, :3] for g in grid])
    if previous is not None:
        cos = (np.einsum("nij,ij->n", rots, previous[:3, :3]) - 1.0) / 2.0  # trace(R_prev^T R)
        best = int(np.argmax(cos))
        chosen_by = "previous"
    else:
        near = _same_way_up(rots @ up_object @ up_env)
        closeness = np.trace(rots, axis1=1, axis2=2)  # larger = smaller rotation angle
        best = int(np.argmax(np.where(near, closeness, -np.inf)))
        chosen_by = "up"
    if side is not None:
        chosen_by = "colour"
    chosen = grid[best]
    samples = symmetry.sample(8) if symmetry.kind == "continuous" else list(symmetry.rotations)
    equivalents = [chosen @ s for s in samples if rotation_angle_deg(s[:3, :3]) > 1e-3]
    return CanonicalPose(chosen, chosen_by, tuple(equivalents))


def canonical_pose(
    env_from_object: Mat4,
    model: PreparedModel,
    up_env: NDArray[np.float64],
    previous: Mat4 | None,
    colour: Callable[[Mat4], float],
    colour_margin: float,
) -> CanonicalPose:
    """Step 5: the :class:`CanonicalPose` of a fitted ``env_from_object`` of ``model``;
    ``up_env`` unit (3,), ``previous`` an earlier 4×4 pose or None, ``colour`` the colour
    agreement of a pose (:func:`colour_agreement`)."""
    picked = _choose_equivalent(
        env_from_object, model.symmetry, model.up_object, up_env, previous, colour, colour_margin
    )
    symmetry, chosen = model.symmetry, picked.env_from_object
    if symmetry.kind != "continuous" or symmetry.axis is None:
        return picked
    assert symmetry.origin is not None
    return replace(
        picked,
        axis_env=chosen[:3, :3] @ symmetry.axis,
        origin_env=transform_points(chosen, symmetry.origin[None])[0],
    )
