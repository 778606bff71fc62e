"""The in-plane pose of an object resting on its support, from its outline seen from above.

A flat object's scan holds its turn on the support badly for point-to-plane fits: its top
face faces up and says nothing about the turn, and stereo smears its low sides into the
floor. Seen from above, its outline still holds the turn: the scan's points of the object
fall inside the model's outline, the support's points seen around it outside.
:func:`fit_top_view` turns the pose about the plane's normal and shifts it across the plane
to agree with both; :func:`outline_costs` compares poses resting on other faces (a flat
object turned over shows its outline's mirror image). All points are (N, 3) float64
metres; poses are 4×4 ``env_from_object``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage
from scipy.optimize import minimize
from scipy.spatial import cKDTree

from workers.pipeline.geometry import (
    Mat4,
    Points,
    perpendicular_pair,
    rotation_about_unit_axis,
)
from workers.pipeline.model.symmetry_group import SymmetrySpec, symmetric_pose_error

#: turns about the support's normal each fit starts from, degrees (the cost has local
#: minima a few degrees apart on an elongated outline)
START_TURNS_DEG = (0.0, -4.0, 4.0, -8.0, 8.0)
#: the most times the points are chosen again around the fit
MAX_PASSES = 3
#: the most a fit may turn its start (modulo the object's symmetry), degrees: half a
#: quarter turn, beyond which a box-like outline is nearer its next pose than the one it
#: refines; the candidates' scores choose among those, not the outline
MAX_TURN_DEG = 45.0
#: the finest outline cell, metres, and the most cells along a side of the outline's grid
MIN_CELL_M = 0.001
MAX_CELLS = 600


class OutlineModel(Protocol):
    """What the fit needs of a model (a :class:`~workers.pipeline.model.PreparedModel` is
    one): (N, 3) surface samples and (3,) centre, object frame, metres, and its symmetry."""

    @property
    def points(self) -> Points: ...

    @property
    def centre_object(self) -> NDArray[np.float64]: ...

    @property
    def symmetry(self) -> SymmetrySpec: ...


@dataclass(frozen=True)
class Outline:
    """A model's outline seen along an axis (object frame, unit, ``u`` × ``v``): in-plane
    axes ``u``, ``v`` (object frame), the grid's ``origin`` (2,) and ``cell_m``, and the
    distances (metres) of each cell to the outline from outside (0 inside) and to the
    outline of its foot from inside (0 outside); ``height_m``: the model's extent along the
    axis."""

    u: NDArray[np.float64]
    v: NDArray[np.float64]
    origin: NDArray[np.float64]
    cell_m: float
    outside_m: NDArray[np.float64]
    inside_m: NDArray[np.float64]
    height_m: float

    @classmethod
    def create(
        cls, model_points: Points, axis_object: NDArray[np.float64], margin_m: float, foot_m: float
    ) -> Outline:
        """The outline of the (N, 3) model surface samples (object frame) along the unit
        ``axis_object``, on a grid reaching ``margin_m`` beyond it, and (for ``inside_m``)
        the outline of its foot, the samples up to ``foot_m`` above its lowest: the support
        shows under an overhang (a drill's body, a mug's handle). The samples' projections
        are closed over their spacing (a closed surface's projection covers its outline,
        so holes through the object, a shackle's, stay open)."""
        u, v = perpendicular_pair(axis_object)
        flat = np.column_stack([model_points @ u, model_points @ v])
        heights = model_points @ axis_object
        lo, hi = flat.min(axis=0) - margin_m, flat.max(axis=0) + margin_m
        cell = max(MIN_CELL_M, float(np.max(hi - lo)) / MAX_CELLS)
        shape = np.ceil((hi - lo) / cell).astype(int) + 1
        sample = model_points[:: max(1, len(model_points) // 2000)]
        spacing = float(np.median(cKDTree(model_points).query(sample, k=2)[0][:, 1]))
        reach = max(1, int(np.ceil(spacing / cell)))
        square = np.ones((2 * reach + 1, 2 * reach + 1), dtype=bool)

        def mask(keep: NDArray[np.bool_]) -> NDArray[np.bool_]:
            out = np.zeros(shape, dtype=bool)
            ij = np.round((flat[keep] - lo) / cell).astype(int)
            out[ij[:, 0], ij[:, 1]] = True
            closed = ndimage.binary_closing(out, structure=square, border_value=0)
            return np.asarray(closed | out, dtype=bool)

        whole = mask(np.ones(len(flat), dtype=bool))
        foot = mask(heights <= heights.min() + foot_m)
        return cls(
            u=u,
            v=v,
            origin=lo,
            cell_m=cell,
            outside_m=ndimage.distance_transform_edt(~whole) * cell,
            inside_m=ndimage.distance_transform_edt(foot) * cell,
            height_m=float(heights.max() - heights.min()),
        )

    def cells(self, env_from_object: Mat4, points_env: Points) -> NDArray[np.float64]:
        """(2, M) grid coordinates of (M, 3) env points under ``env_from_object``."""
        q = (points_env - env_from_object[:3, 3]) @ env_from_object[:3, :3]
        return ((np.column_stack([q @ self.u, q @ self.v]) - self.origin) / self.cell_m).T

    def cost(
        self, env_from_object: Mat4, object_env: Points, support_env: Points, cap_m: float
    ) -> float:
        """Σ of squared distances (capped at ``cap_m``, in units of it) of the (M, 3) object
        points outside the outline and of the (S, 3) support points inside its foot."""
        return self.cost_at(
            self.cells(env_from_object, object_env),
            self.cells(env_from_object, support_env),
            cap_m,
        )

    def cost_at(
        self, object_cells: NDArray[np.float64], support_cells: NDArray[np.float64], cap_m: float
    ) -> float:
        """:meth:`cost` of points already on the grid: (2, M) and (2, S) cell coordinates."""
        outside = _bilinear(self.outside_m, object_cells, cap_m)
        inside = _bilinear(self.inside_m, support_cells, 0.0)
        return (
            float(np.sum(np.minimum(outside, cap_m) ** 2) + np.sum(np.minimum(inside, cap_m) ** 2))
            / cap_m**2
        )


def stands_flat(
    model_points: Points,
    diameter_m: float,
    env_from_object: Mat4,
    normal_env: NDArray[np.float64],
    max_height_ratio: float,
) -> bool:
    """Whether the (N, 3) model points (object frame) posed by ``env_from_object`` stand at
    most ``max_height_ratio`` × ``diameter_m`` tall along the unit ``normal_env``: a flat
    object, whose turn and shift on its support come from above (a ratio ≤ 0 holds none)."""
    heights = model_points @ (env_from_object[:3, :3].T @ normal_env)
    return float(np.ptp(heights)) <= max_height_ratio * diameter_m


def turned_in_plane(
    env_from_object: Mat4,
    normal: NDArray[np.float64],
    centre_env: NDArray[np.float64],
    x: NDArray[np.float64],
) -> Mat4:
    """``env_from_object`` turned by ``x[0]`` radians about the unit ``normal`` through
    ``centre_env`` and shifted by ``x[1:]`` metres along the plane's in-plane axes."""
    a, b = perpendicular_pair(normal)
    turn = rotation_about_unit_axis(normal, float(x[0]))
    out = np.eye(4)
    out[:3, :3] = turn @ env_from_object[:3, :3]
    out[:3, 3] = turn @ (env_from_object[:3, 3] - centre_env) + centre_env + x[1] * a + x[2] * b
    return out


def least_turn_and_shift(
    cost: Callable[[NDArray[np.float64]], float], starts_deg: Sequence[float], ftol: float
) -> NDArray[np.float64]:
    """The (3,) turn (radians) and shift (metres) of :func:`turned_in_plane` of least
    ``cost``: zero, or Powell's minimum from each turn of ``starts_deg`` (degrees) when it
    costs less (``ftol``: Powell's relative tolerance on the cost)."""
    best_x, best = np.zeros(3), cost(np.zeros(3))
    for turn_deg in starts_deg:
        r = minimize(
            cost,
            np.array([np.radians(turn_deg), 0.0, 0.0]),
            method="Powell",
            options={"xtol": 1e-5, "ftol": ftol},
        )
        if r.fun < best:
            best_x, best = np.asarray(r.x, dtype=np.float64), float(r.fun)
    return best_x


def fit_top_view(
    model: OutlineModel,
    starts: Sequence[Mat4],
    support: NDArray[np.float64],
    scene_env: Points,
    support_env: Points,
    reach_m: float,
    window_m: float,
) -> Mat4:
    """The pose, of ``starts`` (env_from_object, each resting on the plane ``support`` =
    [n, d], unit n, on the same face) turned about n and shifted across the plane, whose
    outline seen along n (of ``model.points``, object frame) best holds the (M, 3)
    ``scene_env`` points up to the model's height above the plane and leaves out the
    (S, 3) ``support_env`` points: squared distances capped at ``reach_m`` summed over the
    points within ``window_m`` of the outline, minimised from each start turned by
    :data:`START_TURNS_DEG`, the points chosen again around the result up to
    :data:`MAX_PASSES` times (as ICP pairs points again). The fits are compared on the
    points near any of them. A start stays when no scan point is near its outline or its
    fit turned it more than :data:`MAX_TURN_DEG` (modulo ``model.symmetry``: a bowl's spin
    is no turn)."""
    n = support[:3]
    outline = Outline.create(model.points, starts[0][:3, :3].T @ n, window_m + reach_m, reach_m)
    height = scene_env @ n + support[3]
    above = scene_env[height <= outline.height_m + window_m]

    def chosen(poses: Sequence[Mat4]) -> tuple[Points, Points]:
        placed = [(outline, p) for p in poses]
        obj, floor = _near_outlines(placed, above, support_env, reach_m, window_m)
        return above[obj], support_env[floor]

    fits = []
    for start in starts:
        pose = start
        for i in range(MAX_PASSES):
            obj, floor = chosen([pose])
            if len(obj) < 10:
                break
            moved = _fit_pass(outline, pose, model.centre_object, n, obj, floor, reach_m, i == 0)
            done = np.allclose(moved, pose, atol=1e-6)
            pose = moved
            if done:
                break
        turned = symmetric_pose_error(pose, start, model.symmetry, model.centre_object)[1]
        fits.append(pose if turned <= MAX_TURN_DEG else start)
    obj, floor = chosen(fits)
    return min(fits, key=lambda p: outline.cost(p, obj, floor, reach_m))


def outline_costs(
    model: OutlineModel,
    poses: Sequence[Mat4],
    support: NDArray[np.float64],
    scene_env: Points,
    support_env: Points,
    reach_m: float,
    window_m: float,
) -> list[float]:
    """For each of ``poses`` (env_from_object, each resting on the plane ``support`` =
    [n, d], on any face), the :meth:`Outline.cost` of its outline seen along n per scan
    point, on the same points for all: the (M, 3) ``scene_env`` points up to the tallest
    outline's height (plus ``window_m``) within ``window_m`` of any outline, the (S, 3)
    ``support_env`` points within ``window_m + reach_m``. Poses the scan cannot tell apart
    cost alike; a pose on its mirrored face or turned away costs more. Empty ``poses``:
    empty list; no point near any outline: all inf."""
    n = support[:3]
    outlines = [
        Outline.create(model.points, p[:3, :3].T @ n, window_m + reach_m, reach_m) for p in poses
    ]
    if not outlines:
        return []
    height = scene_env @ n + support[3]
    above = scene_env[height <= max(o.height_m for o in outlines) + window_m]
    placed = list(zip(outlines, poses, strict=True))
    obj, floor = _near_outlines(placed, above, support_env, reach_m, window_m)
    count = int(obj.sum())
    if count == 0:
        return [float("inf")] * len(poses)
    return [
        outline.cost(pose, above[obj], support_env[floor], reach_m) / count
        for outline, pose in placed
    ]


def _near_outlines(
    placed: Sequence[tuple[Outline, Mat4]],
    above: Points,
    support_env: Points,
    reach_m: float,
    window_m: float,
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Masks of the (M, 3) ``above`` points within ``window_m`` of any of the outlines
    placed at their poses, and of the (S, 3) ``support_env`` points within ``window_m +
    reach_m``: the points a fit or a comparison of those poses weighs (the support's
    points only ever push an outline off them, so all near it count)."""
    obj = np.zeros(len(above), dtype=bool)
    floor = np.zeros(len(support_env), dtype=bool)
    for outline, pose in placed:
        obj |= _bilinear(outline.outside_m, outline.cells(pose, above), np.inf) <= window_m
        near = _bilinear(outline.outside_m, outline.cells(pose, support_env), np.inf)
        floor |= near <= window_m + reach_m
    return obj, floor


def _fit_pass(
    outline: Outline,
    pose: Mat4,
    centre_object: NDArray[np.float64],
    normal: NDArray[np.float64],
    obj: Points,
    floor: Points,
    reach_m: float,
    first: bool,
) -> Mat4:
    """One pass of :func:`fit_top_view` on chosen points: the least-cost pose from ``pose``
    turned by each of :data:`START_TURNS_DEG` (``first``) or from ``pose`` alone. The
    points are carried into the plane once: a turn about the normal and a shift across it
    move them in the plane only."""
    centre = pose[:3, :3] @ centre_object + pose[:3, 3]
    axes = pose[:3, :3] @ np.column_stack([outline.u, outline.v])  # (3, 2) env frame
    a, b = perpendicular_pair(normal)
    shifts = axes.T @ np.column_stack([a, b])  # (2, 2): the plane's shifts on the grid's axes
    offset = (axes.T @ (centre - pose[:3, 3]) - outline.origin) / outline.cell_m
    obj_flat, floor_flat = axes.T @ (obj - centre).T, axes.T @ (floor - centre).T

    def cells(flat: NDArray[np.float64], x: NDArray[np.float64]) -> NDArray[np.float64]:
        c, s = np.cos(x[0]), np.sin(x[0])
        back = np.array([[c, s], [-s, c]])  # the points turned by -x[0]
        return (back @ (flat - (shifts @ x[1:])[:, None])) / outline.cell_m + offset[:, None]

    def cost(x: NDArray[np.float64]) -> float:
        return outline.cost_at(cells(obj_flat, x), cells(floor_flat, x), reach_m)

    best_x = least_turn_and_shift(cost, START_TURNS_DEG if first else (0.0,), ftol=1e-4)
    return turned_in_plane(pose, normal, centre, best_x)


def _bilinear(
    grid: NDArray[np.float64], cells: NDArray[np.float64], fill: float
) -> NDArray[np.float64]:
    """``grid`` interpolated bilinearly at (2, M) cell coordinates; ``fill`` off the grid."""
    i, j = np.floor(cells[0]), np.floor(cells[1])
    on = (i >= 0) & (j >= 0) & (i < grid.shape[0] - 1) & (j < grid.shape[1] - 1)
    out = np.full(cells.shape[1], fill, dtype=np.float64)
    i0, j0 = i[on].astype(np.intp), j[on].astype(np.intp)
    fi, fj = cells[0][on] - i0, cells[1][on] - j0
    flat, row = grid.ravel(), grid.shape[1]
    at = i0 * row + j0  # flat index of (i0, j0); taking from the flat grid is the fast gather
    out[on] = (
        flat.take(at) * (1 - fi) * (1 - fj)
        + flat.take(at + row) * fi * (1 - fj)
        + flat.take(at + 1) * (1 - fi) * fj
        + flat.take(at + row + 1) * fi * fj
    )
    return out
