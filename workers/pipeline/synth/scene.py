"""Scene layout: the room, where objects stand, and the before/after scenarios.

All poses are ``env_from_object`` (4×4 float64, metres), environment z up, floor at z = 0.
Objects rest on a support (floor, table top or shelf top) by their lowest vertex and only
turn about z, except those ``SynthOptions.lying`` names: each is set down on another face
of its convex hull that can take its weight (:func:`resting_faces`), drawn at random.
A new or moved object never stands where a removed or moved one stood (only a
swap puts an object there), so each change has a place of its own. Distractors (objects
outside the library) are added in the after capture, on the floor.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from workers.pipeline.errors import InputError
from workers.pipeline.geometry import Mat4, make_rigid, perpendicular_pair, rotation_from_rotvec
from workers.pipeline.synth.markers import MarkerSheet, marker_sheet, rot_z
from workers.pipeline.synth.options import LAYOUTS, SCENARIOS, RoomOptions, SynthOptions
from workers.pipeline.synth.shapes import (
    Mesh,
    ObjectModel,
    box,
    distractor_model,
    footprint_circle,
    merge,
)
from workers.pipeline.synth.texture import SolidTexture


@dataclass(frozen=True, eq=False)
class Placement:
    """One object instance: its class model and ``env_from_object``."""

    instance_id: str
    model: ObjectModel
    env_from_object: Mat4
    support: str = "floor"
    # (centre xy (2,), radius) in metres of a model set down on another face than its base;
    # None: the upright model's footprint, turned with the pose
    footprint_m: tuple[np.ndarray, float] | None = None

    def footprint_env(self) -> tuple[np.ndarray, float]:
        """(centre xy (2,), radius) in metres of the model's footprint circle on its support."""
        if self.footprint_m is not None:
            return self.footprint_m
        centre, radius = self.model.footprint
        xy = self.env_from_object[:2, :2] @ centre + self.env_from_object[:2, 3]
        return xy, radius


@dataclass(frozen=True, eq=False)
class StaticSurface:
    """A surface of the room, ``mesh`` in the environment frame, textured in that frame."""

    name: str
    mesh: Mesh
    texture: SolidTexture


@dataclass(frozen=True)
class Support:
    """A level surface objects stand on: ``name``, the centre (x, y) and size (x, y) of its
    rectangle in metres (the floor's is the placement disc's bounding square) and its height
    ``z_m`` above the floor."""

    name: str
    centre_m: tuple[float, float]
    size_m: tuple[float, float]
    z_m: float

    def to_json(self) -> dict[str, object]:
        return {
            "name": self.name,
            "centre_m": list(self.centre_m),
            "size_m": list(self.size_m),
            "z_m": self.z_m,
        }


def supports(room: RoomOptions) -> tuple[Support, ...]:
    """The floor, then the table top and the shelf's top board when the room has them."""
    d = 2.0 * room.placement_radius_m
    out = [Support("floor", (0.0, 0.0), (d, d), 0.0)]
    if room.table:
        (w, dpt, h), (x, y) = room.table_size_m, room.table_centre_m
        out.append(Support("table", (x, y), (w, dpt), h))
    if room.shelf:
        (w, dpt, h), (x, y) = room.shelf_size_m, room.shelf_centre_m
        out.append(Support("shelf", (x, y), (w - 0.06, dpt), h))
    return tuple(out)


@dataclass(frozen=True, eq=False)
class Scenario:
    """A before/after pair with its ground-truth changes (docs/contract.md change fields).

    ``models`` are the library classes; ``distractors`` the models outside it (their
    placements are in ``after``); ``supports`` every surface objects stand on.
    """

    name: str
    seed: int
    models: tuple[ObjectModel, ...]
    room: tuple[StaticSurface, ...]
    markers: MarkerSheet
    before: tuple[Placement, ...]
    after: tuple[Placement, ...]
    changes: tuple[dict[str, Any], ...] = field(default=())
    supports: tuple[Support, ...] = ()
    distractors: tuple[ObjectModel, ...] = ()

    def capture(self, name: str) -> tuple[Placement, ...]:
        """The placements of capture ``before`` or ``after``."""
        if name not in ("before", "after"):
            raise InputError(f"capture must be 'before' or 'after', got {name!r}")
        return self.before if name == "before" else self.after


# (floor colours, wall colours) of texture variants 1..; variant 0 is the original look
_PALETTES: tuple[tuple[tuple[tuple[float, float, float], ...], ...], ...] = (
    (((0.62, 0.5, 0.36), (0.38, 0.27, 0.18)), ((0.85, 0.85, 0.82), (0.6, 0.62, 0.66))),
    (((0.35, 0.38, 0.42), (0.22, 0.24, 0.27)), ((0.7, 0.76, 0.7), (0.5, 0.42, 0.36))),
    (((0.7, 0.68, 0.6), (0.5, 0.36, 0.3)), ((0.62, 0.66, 0.78), (0.82, 0.8, 0.72))),
)


def _room_textures(room: RoomOptions) -> tuple[SolidTexture, SolidTexture]:
    """(floor, wall) textures of ``room.texture_variant``."""
    if room.texture_variant == 0:
        return (
            SolidTexture((0.55, 0.55, 0.52), (0.42, 0.4, 0.36), seed=1, scale=0.7),
            SolidTexture((0.78, 0.74, 0.64), (0.45, 0.55, 0.62), seed=2, scale=1.5),
        )
    if room.texture_variant < 0:
        raise InputError(f"texture_variant must be ≥ 0, got {room.texture_variant}")
    (fa, fb), (wa, wb) = _PALETTES[(room.texture_variant - 1) % len(_PALETTES)]
    seed = 10 * room.texture_variant
    return (
        SolidTexture(fa, fb, seed=seed + 1, scale=0.6 + 0.1 * room.texture_variant),
        SolidTexture(wa, wb, seed=seed + 2, scale=1.2 + 0.2 * room.texture_variant),
    )


def _shelf(room: RoomOptions) -> StaticSurface:
    """An open shelf unit: two side panels (along y), a middle board and the top board."""
    (w, d, h), (x, y) = room.shelf_size_m, room.shelf_centre_m
    t = 0.03
    parts = [
        box((w, d, t), (x, y, h - t / 2)),
        box((w - 2 * t, d, t), (x, y, h / 2)),
    ]
    for sx in (-1, 1):
        parts.append(box((t, d, h - t), (x + sx * (w / 2 - t / 2), y, (h - t) / 2)))
    paint = SolidTexture((0.86, 0.84, 0.8), (0.55, 0.5, 0.46), seed=4, scale=0.5)
    return StaticSurface("shelf", merge(parts), paint)


def room_surfaces(room: RoomOptions) -> tuple[StaticSurface, ...]:
    """Floor, the walls of ``room.layout`` and the optional table and shelf, as meshes in the
    environment frame. InputError for an unknown layout."""
    if room.layout not in LAYOUTS:
        raise InputError(f"unknown room layout {room.layout!r}; choose one of {list(LAYOUTS)}")
    walls = {"closed": (0, 1, 2, 3), "one_wall": (2,), "two_walls": (0, 2)}[room.layout]
    half, height = room.size_m / 2.0, room.wall_height_m
    floor_tex, wall_tex = _room_textures(room)
    t = 0.05
    out = [StaticSurface("floor", box((room.size_m, room.size_m, t), (0, 0, -t / 2)), floor_tex)]
    for k, (sx, sy, cx, cy) in enumerate(
        [
            (t, room.size_m, half + t / 2, 0.0),
            (t, room.size_m, -half - t / 2, 0.0),
            (room.size_m, t, 0.0, half + t / 2),
            (room.size_m, t, 0.0, -half - t / 2),
        ]
    ):
        if k not in walls:
            continue
        out.append(
            StaticSurface(f"wall_{k}", box((sx, sy, height), (cx, cy, height / 2)), wall_tex)
        )
    if room.table:
        (w, d, h), (x, y) = room.table_size_m, room.table_centre_m
        top = 0.03
        parts = [box((w, d, top), (x, y, h - top / 2))]
        for sx in (-1, 1):
            for sy in (-1, 1):
                leg = (x + sx * (w / 2 - 0.04), y + sy * (d / 2 - 0.04), (h - top) / 2)
                parts.append(box((0.04, 0.04, h - top), leg))
        wood = SolidTexture((0.62, 0.43, 0.25), (0.4, 0.26, 0.14), seed=3, scale=0.5)
        out.append(StaticSurface("table", merge(parts), wood))
    if room.shelf:
        out.append(_shelf(room))
    return tuple(out)


def _rest_pose(
    model: ObjectModel,
    xy: np.ndarray,
    yaw_rad: float,
    support_z: float,
    lying: tuple[np.ndarray, np.ndarray, float] | None = None,
) -> Mat4:
    """``env_from_object`` standing the model on z = ``support_z`` (set down by the tilt of
    :meth:`_Placer._set_down`'s ``lying`` when given), turned by yaw about z, with its
    footprint centre at ``xy``."""
    tilt, centre = (np.eye(3), model.footprint[0]) if lying is None else lying[:2]
    turn = rot_z(yaw_rad)
    rot = turn @ tilt
    origin_xy = xy - turn[:2, :2] @ centre
    z = support_z - float((model.mesh.vertices @ rot.T)[:, 2].min())
    return make_rigid(rot, [float(origin_xy[0]), float(origin_xy[1]), z])


#: a resting face holds the foot of the model's centre at least this far inside its edges
_REST_MARGIN_M = 0.005


def resting_faces(vertices: np.ndarray) -> list[np.ndarray]:
    """Unit outward normals (object frame) of the faces of the convex hull of (N, 3)
    ``vertices`` (metres) that the model can rest on: coplanar hull triangles (within 1°)
    merged, the foot of the hull's centroid inside the face by :data:`_REST_MARGIN_M`.
    The base (normal within 10° of −z) is left out."""
    hull = ConvexHull(vertices)
    apex = vertices[hull.vertices].mean(axis=0)  # the hull's volume centroid, by tetrahedra
    tri = vertices[hull.simplices] - apex
    volumes = np.abs(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])))
    centre = apex + (volumes[:, None] * tri.sum(axis=1) / 4.0).sum(axis=0) / volumes.sum()
    normals = hull.equations[:, :3]
    taken = np.zeros(len(normals), dtype=bool)
    out = []
    for i in range(len(normals)):
        if taken[i]:
            continue
        group = (normals @ normals[i] > np.cos(np.radians(1.0))) & ~taken
        taken |= group
        n = normals[group].mean(axis=0)
        n /= np.linalg.norm(n)
        if n[2] < -np.cos(np.radians(10.0)):
            continue
        corners = vertices[np.unique(hull.simplices[group])]
        axes = np.stack(perpendicular_pair(n))
        flat, foot = corners @ axes.T, centre @ axes.T
        if len(flat) < 3:
            continue
        try:
            edges = ConvexHull(flat).equations
        except QhullError:
            continue
        if np.all(edges[:, :2] @ foot + edges[:, 2] <= -_REST_MARGIN_M):
            out.append(n)
    return out


def _turn_down(normal: np.ndarray) -> np.ndarray:
    """(3, 3) rotation taking unit ``normal`` to −z (the shortest turn)."""
    down = np.array([0.0, 0.0, -1.0])
    axis = np.cross(normal, down)
    s, c = float(np.linalg.norm(axis)), float(normal @ down)
    if s < 1e-9:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    return rotation_from_rotvec(axis / s * np.arctan2(s, c))


class _Placer:
    """Rejection sampling of free resting poses: circles around each object's z axis must
    not overlap each other, the marker tiles or the raised supports (floor objects), and
    objects on a table or shelf must lie within its top."""

    def __init__(
        self,
        room: RoomOptions,
        markers: MarkerSheet,
        rng: np.random.Generator,
        lying: Sequence[str] = (),
    ):
        self.room, self.markers, self.rng = room, markers, rng
        self.margin = 0.03
        self.supports = {s.name: s for s in supports(room)}
        self.lying = frozenset(lying)

    def _set_down(self, model: ObjectModel) -> tuple[np.ndarray, np.ndarray, float] | None:
        """For a model ``lying`` names: (the rotation (3, 3) setting one of its
        :func:`resting_faces`, drawn at random, down, the footprint centre (2,) and radius
        of the model so turned); None for any other model (no draw is made)."""
        if model.name not in self.lying:
            return None
        faces = resting_faces(np.asarray(model.mesh.vertices, dtype=np.float64))
        if not faces:
            raise InputError(f"{model.name} has no face to lie on but its base")
        tilt = _turn_down(faces[int(self.rng.integers(len(faces)))])
        centre, radius = footprint_circle((model.mesh.vertices @ tilt.T)[:, :2])
        return tilt, centre, radius

    def _free(self, r: float, xy: np.ndarray, support: str, others: Sequence[Placement]) -> bool:
        for other in others:
            if other.support != support:
                continue
            other_xy, other_r = other.footprint_env()
            if float(np.linalg.norm(other_xy - xy)) < r + other_r + self.margin:
                return False
        if support != "floor":
            return bool(np.all(self._gap(support, xy) <= -r))
        if float(np.linalg.norm(xy)) > self.room.placement_radius_m:
            return False
        for name in self.supports:
            gap = self._gap(name, xy)
            if name != "floor" and float(np.linalg.norm(np.maximum(gap, 0.0))) < r + self.margin:
                return False
        tile = self.markers.tile_radius_m()
        return all(
            float(np.linalg.norm(pose[:2, 3] - xy)) >= r + tile + self.margin
            for pose in self.markers.env_from_marker.values()
        )

    def _gap(self, support: str, xy: np.ndarray) -> np.ndarray:
        """(2,) signed distances in metres from the rectangle of ``support`` to ``xy`` along
        x and y (negative inside)."""
        s = self.supports[support]
        gap: np.ndarray = np.abs(xy - np.asarray(s.centre_m)) - np.asarray(s.size_m) / 2
        return gap

    def place(
        self,
        model: ObjectModel,
        instance_id: str,
        others: Sequence[Placement],
        near_xy: np.ndarray | None = None,
        away_from: Placement | None = None,
        min_move_m: float = 0.0,
        floor_only: bool = False,
    ) -> Placement:
        """A free pose for ``model`` (``xy`` below is where its footprint centre goes); near
        ``near_xy`` (swaps) or ≥ ``min_move_m`` away from ``away_from`` (moves). Raises
        _NoRoom when no free pose is found."""
        names = ["floor"] if floor_only else list(self.supports)
        lying = self._set_down(model)
        footprint_r = model.footprint_radius_m() if lying is None else lying[2]
        for attempt in range(400):
            support = names[int(self.rng.integers(len(names)))]
            if near_xy is not None:
                spread = 0.02 + 0.3 * attempt / 400
                xy = near_xy + self.rng.normal(0.0, spread, 2)
                support = "floor" if away_from is None else away_from.support
            elif support != "floor":
                s = self.supports[support]
                half = np.asarray(s.size_m) / 2
                xy = np.asarray(s.centre_m) + self.rng.uniform(-half, half)
            else:
                radius = self.room.placement_radius_m * np.sqrt(self.rng.uniform())
                angle = self.rng.uniform(0.0, 2.0 * np.pi)
                xy = radius * np.asarray([np.cos(angle), np.sin(angle)])
            if near_xy is None and away_from is not None:
                shift = float(np.linalg.norm(away_from.footprint_env()[0] - xy))
                if shift < min_move_m:
                    continue
            if not self._free(footprint_r, xy, support, others):
                continue
            support_z = self.supports[support].z_m
            yaw = self.rng.uniform(-np.pi, np.pi)
            pose = _rest_pose(model, xy, yaw, support_z, lying)
            footprint = None if lying is None else (xy, footprint_r)
            return Placement(instance_id, model, pose, support, footprint)
        raise _NoRoom(f"no free place for {model.name}")


def _change(kind: str, new: Placement | None, old: Placement | None) -> dict[str, Any]:
    """A ground-truth change record with docs/contract.md field names."""
    ref = new if new is not None else old
    assert ref is not None
    return {
        "type": kind,
        "object": ref.model.name,
        "instance_id": ref.instance_id,
        "pose": None if new is None else new.env_from_object.tolist(),
        "previous_pose": None if old is None or kind == "swapped" else old.env_from_object.tolist(),
        "replaced_object": old.model.name if kind == "swapped" and old is not None else None,
        "replaced_instance_id": old.instance_id if kind == "swapped" and old is not None else None,
    }


class _NoRoom(InputError):
    """No free resting pose was found (the layout is retried with other draws)."""


def build_scenario(
    scenario: str, models: Sequence[ObjectModel], seed: int, options: SynthOptions
) -> Scenario:
    """Lay out the before capture and derive the after capture for ``scenario``.

    The last non-symmetric model is held back as the spare (it appears in ``added``,
    ``swapped`` and ``multiple``); every other model stands in the before capture. A layout
    that paints itself into a corner is redrawn (deterministically from ``seed``).
    ``options.target`` names the model that is removed, moved or swapped out;
    ``options.distractors`` are added in the after capture with unidentified changes.
    """
    if scenario not in SCENARIOS:
        raise InputError(f"unknown scenario {scenario!r}; choose one of {list(SCENARIOS)}")
    names = [m.name for m in models]
    if len(models) < 2 or len(set(names)) != len(names):
        raise InputError(f"need at least two objects with distinct names, got {names}")
    spare_index = max(
        (i for i, m in enumerate(models) if m.symmetry is None), default=len(models) - 1
    )
    staying = [m for i, m in enumerate(models) if i != spare_index]
    if scenario == "symmetric_moved" and all(m.symmetry is None for m in staying):
        raise InputError(f"scenario 'symmetric_moved' needs a symmetric object among {names}")
    if scenario in ("moved", "multiple") and all(m.symmetry is not None for m in staying):
        raise InputError(f"scenario {scenario!r} needs two non-symmetric objects among {names}")
    if options.target is not None and options.target not in [m.name for m in staying]:
        raise InputError(f"target {options.target!r} is not among the staying objects")
    if set(options.lying) - set(names):
        unknown = sorted(set(options.lying) - set(names))
        raise InputError(f"lying names {unknown}, not among the objects {names}")
    distractors = tuple(distractor_model(name) for name in options.distractors)
    markers = marker_sheet(options.room)
    for attempt in range(50):
        rng = np.random.default_rng([seed, 1, attempt])
        placer = _Placer(options.room, markers, rng, options.lying)
        try:
            before, after, changes = _layout(
                scenario, staying, models[spare_index], placer, options
            )
            _add_distractors(distractors, placer, before, after, changes)
        except _NoRoom:
            continue
        return Scenario(
            scenario,
            seed,
            tuple(models),
            room_surfaces(options.room),
            markers,
            tuple(before),
            tuple(after),
            tuple(changes),
            supports(options.room),
            distractors,
        )
    raise InputError(f"no room for {names} in this room; use fewer or smaller objects")


def _layout(
    scenario: str,
    staying: list[ObjectModel],
    spare: ObjectModel,
    placer: _Placer,
    options: SynthOptions,
) -> tuple[list[Placement], list[Placement], list[dict[str, Any]]]:
    """Placements before and after, and the change records; raises _NoRoom when stuck."""
    rng = placer.rng
    before: list[Placement] = []
    for k, model in enumerate(staying):
        before.append(placer.place(model, f"inst-{k:02d}", before))
    next_id = f"inst-{len(before):02d}"
    after = list(before)
    # where a removed or moved object stood: kept free of new and moved objects (only a
    # swap puts a new object there), so one place holds one change
    vacated: list[Placement] = []
    changes: list[dict[str, Any]] = []

    def pick(symmetric: bool | None) -> Placement:
        pool = [
            p for p in after if symmetric is None or (p.model.symmetry is not None) == symmetric
        ]
        chosen = [p for p in pool if p.model.name == options.target]
        if chosen:
            return chosen[0]
        return pool[int(rng.integers(len(pool)))]

    def move(old: Placement) -> None:
        others = [p for p in after if p is not old] + vacated
        new = placer.place(
            old.model, old.instance_id, others, away_from=old, min_move_m=options.move_min_m
        )
        after[after.index(old)] = new
        vacated.append(old)
        changes.append(_change("moved", new, old))

    def remove(old: Placement) -> None:
        after.remove(old)
        vacated.append(old)
        changes.append(_change("removed", None, old))

    def add(model: ObjectModel) -> None:
        new = placer.place(model, next_id, after + vacated)
        after.append(new)
        changes.append(_change("added", new, None))

    if scenario == "added":
        add(spare)
    elif scenario == "removed":
        remove(pick(None))
    elif scenario in ("moved", "symmetric_moved"):
        move(pick(scenario == "symmetric_moved"))
    elif scenario == "swapped":
        old = pick(None)
        others = [p for p in after if p is not old]
        new = placer.place(spare, next_id, others, near_xy=old.footprint_env()[0], away_from=old)
        after[after.index(old)] = new
        changes.append(_change("swapped", new, old))
    elif scenario == "multiple":
        remove(pick(False))
        move(pick(None))
        add(spare)
    return before, after, changes


def _add_distractors(
    distractors: Sequence[ObjectModel],
    placer: _Placer,
    before: list[Placement],
    after: list[Placement],
    changes: list[dict[str, Any]],
) -> None:
    """Stand each distractor on the floor of the after capture, clear of every object and of
    every place an object left, with an added change whose expected outcome is unidentified
    (``object`` None). Raises _NoRoom when no free pose is found."""
    for k, model in enumerate(distractors):
        new = placer.place(model, f"distractor-{k:02d}", after + before, floor_only=True)
        after.append(new)
        change = _change("added", new, None)
        change.update(object=None, distractor=model.name, unidentified=True)
        changes.append(change)
