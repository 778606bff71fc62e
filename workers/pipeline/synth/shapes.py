"""Object models of the generator: built-in procedural shapes and textured mesh files.

Every model lives in its own frame (metres, z up, resting on z = min z). Built-in shapes
are 15–40 cm: four without a proper rotational symmetry and one cylinder (a drum).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from workers.pipeline.errors import InputError
from workers.pipeline.synth.texture import F32, SolidTexture

F64 = NDArray[np.float64]
I32 = NDArray[np.int32]
Symmetry = dict[str, Any]


@dataclass(frozen=True, eq=False)
class Mesh:
    """A triangle mesh: (V, 3) float64 vertices in metres, (T, 3) int32 triangles."""

    vertices: F64
    triangles: I32

    @property
    def vertex_normals(self) -> F64:
        """(V, 3) unit vertex normals, area-weighted mean of the adjacent face normals."""
        v, t = self.vertices, self.triangles
        face = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
        out = np.zeros_like(v)
        for k in range(3):
            np.add.at(out, t[:, k], face)
        norm = np.linalg.norm(out, axis=1, keepdims=True)
        result: F64 = out / np.maximum(norm, 1e-12)
        return result

    def signed_volume(self) -> float:
        """Signed enclosed volume in m³ (positive when faces wind outwards)."""
        v = self.vertices[self.triangles]
        return float(np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0)


def merge(parts: list[Mesh]) -> Mesh:
    """Concatenate meshes into one (no welding)."""
    offsets = np.cumsum([0] + [len(p.vertices) for p in parts[:-1]])
    verts = np.concatenate([p.vertices for p in parts])
    tris = np.concatenate([p.triangles + o for p, o in zip(parts, offsets, strict=True)])
    return Mesh(verts.astype(np.float64), tris.astype(np.int32))


def box(size: tuple[float, float, float], centre: tuple[float, float, float]) -> Mesh:
    """Axis-aligned box, (sx, sy, sz) metres around ``centre``; flat faces, outward winding."""
    c = np.asarray(centre, np.float64)
    h = np.asarray(size, np.float64) / 2.0
    eye = np.eye(3)
    verts: list[F64] = []
    tris: list[list[int]] = []
    for axis in range(3):
        for sign in (1.0, -1.0):
            u, v = eye[(axis + 1) % 3], eye[(axis + 2) % 3]
            if sign < 0:
                u, v = v, u
            centre_f = c + sign * h[axis] * eye[axis]
            hu, hv = float(h @ np.abs(u)), float(h @ np.abs(v))
            n0 = len(verts)
            for du, dv in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                verts.append(centre_f + du * hu * u + dv * hv * v)
            tris += [[n0, n0 + 1, n0 + 2], [n0, n0 + 2, n0 + 3]]
    return Mesh(np.asarray(verts), np.asarray(tris, np.int32))


def _ear_clip(poly: F64) -> list[list[int]]:
    """Triangles (indices) of a simple counter-clockwise (P, 2) polygon."""
    idx = list(range(len(poly)))
    out: list[list[int]] = []

    def cross(o: F64, a: F64, b: F64) -> float:
        return float((a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]))

    while len(idx) > 3:
        for k in range(len(idx)):
            i, j, m = idx[k - 1], idx[k], idx[(k + 1) % len(idx)]
            a, b, c = poly[i], poly[j], poly[m]
            if cross(a, b, c) <= 1e-12:
                continue
            others = [poly[q] for q in idx if q not in (i, j, m)]
            if any(
                cross(a, b, p) >= 0 and cross(b, c, p) >= 0 and cross(c, a, p) >= 0 for p in others
            ):
                continue
            out.append([i, j, m])
            idx.pop(k)
            break
        else:
            raise InputError("polygon is not simple and counter-clockwise")
    out.append(idx)
    return out


def extrude(profile_xz: list[tuple[float, float]], depth_m: float) -> Mesh:
    """Prism from a counter-clockwise (x, z) profile, extruded symmetrically along y."""
    poly = np.asarray(profile_xz, np.float64)
    n = len(poly)
    half = depth_m / 2.0

    def lift(y: float) -> F64:
        return np.stack([poly[:, 0], np.full(n, y), poly[:, 1]], axis=1)

    caps = np.asarray(_ear_clip(poly), np.int32)
    parts = [Mesh(lift(-half), caps), Mesh(lift(half), caps[:, ::-1].copy())]
    for i in range(n):
        a, b = poly[i], poly[(i + 1) % n]
        quad = np.asarray(
            [[a[0], -half, a[1]], [b[0], -half, b[1]], [b[0], half, b[1]], [a[0], half, a[1]]]
        )
        parts.append(Mesh(quad, np.asarray([[0, 2, 1], [0, 3, 2]], np.int32)))
    return merge(parts)


def cylinder(radius_m: float, z0: float, z1: float, segments: int, bottom: bool) -> Mesh:
    """Cylinder about z from ``z0`` to ``z1`` with smooth sides, a top cap and optional bottom."""
    ang = np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)
    ring = np.stack([radius_m * np.cos(ang), radius_m * np.sin(ang)], axis=1)
    k = np.arange(segments)
    k1 = (k + 1) % segments
    side_v = np.concatenate(
        [
            np.column_stack([ring, np.full(segments, z0)]),
            np.column_stack([ring, np.full(segments, z1)]),
        ]
    )
    side_t = np.concatenate(
        [np.stack([k, k1, k1 + segments], 1), np.stack([k, k1 + segments, k + segments], 1)]
    )
    parts = [Mesh(side_v, side_t.astype(np.int32))]
    for z, up in ((z1, True), (z0, False)) if bottom else ((z1, True),):
        verts = np.vstack([[0.0, 0.0, z], np.column_stack([ring, np.full(segments, z)])])
        tris = np.stack([np.zeros(segments, int), k + 1, k1 + 1], 1)
        parts.append(Mesh(verts, (tris if up else tris[:, ::-1]).astype(np.int32)))
    return merge(parts)


@dataclass(frozen=True, eq=False)
class ObjectModel:
    """An object class: mesh in its own frame plus how its surface is coloured.

    Exactly one appearance is set: ``solid`` (procedural, evaluated at object-frame
    positions), ``uv_texture`` with ``triangle_uvs`` (T, 3, 2), or ``vertex_colours`` (V, 3).
    ``symmetry`` is None or {"kind": "continuous", "axis": [x, y, z], "origin": [x, y, z]}
    (object frame): the rotations about that axis leave the shape unchanged.
    """

    name: str
    mesh: Mesh
    solid: SolidTexture | None = None
    uv_texture: NDArray[np.uint8] | None = None
    triangle_uvs: F64 | None = None
    vertex_colours: F32 | None = None
    symmetry: Symmetry | None = None

    def surface_colours(
        self,
        triangle_ids: NDArray[np.int64],
        bary: F32,
        points: F32,
        footprint_m: F32 | None = None,
    ) -> F32:
        """RGB in [0, 1], (N, 3), at N surface points.

        ``triangle_ids`` (N,), barycentric ``bary`` (N, 2) as Open3D's ``primitive_uvs``
        (weights of vertices 1 and 2), ``points`` (N, 3) in the object frame (metres),
        ``footprint_m`` (N,) pixel size on the surface (see :class:`SolidTexture`).
        """
        if self.solid is not None:
            return self.solid.colours(points, footprint_m)
        w1, w2 = bary[:, 0:1], bary[:, 1:2]
        w0 = np.float32(1.0) - w1 - w2
        if self.uv_texture is not None and self.triangle_uvs is not None:
            uv = self.triangle_uvs[triangle_ids].astype(np.float32)
            st = w0 * uv[:, 0] + w1 * uv[:, 1] + w2 * uv[:, 2]
            return _sample_image(self.uv_texture, st)
        if self.vertex_colours is not None:
            tri = self.mesh.triangles[triangle_ids]
            c = self.vertex_colours
            out: F32 = w0 * c[tri[:, 0]] + w1 * c[tri[:, 1]] + w2 * c[tri[:, 2]]
            return out
        return np.full((len(points), 3), 0.6, np.float32)

    def colours_at_vertices(self) -> F32:
        """(V, 3) RGB in [0, 1] for the model file (texture averaged onto vertices)."""
        v, t = self.mesh.vertices, self.mesh.triangles
        if self.solid is not None:
            return self.solid.colours(v)
        if self.vertex_colours is not None:
            return self.vertex_colours
        corner_ids = np.repeat(np.arange(len(t)), 3)
        bary = np.tile(np.asarray([[0, 0], [1, 0], [0, 1]], np.float32), (len(t), 1))
        corner = self.surface_colours(corner_ids, bary, v[t].reshape(-1, 3).astype(np.float32))
        acc = np.zeros((len(v), 3), np.float64)
        np.add.at(acc, t.reshape(-1), corner)
        count = np.bincount(t.reshape(-1), minlength=len(v))[:, None]
        out: F32 = (acc / np.maximum(count, 1)).astype(np.float32)
        return out

    @cached_property
    def footprint(self) -> tuple[F64, float]:
        """(centre (2,), radius) in metres of a circle in the object's xy plane holding the
        whole model seen from above (:func:`footprint_circle` of its vertices)."""
        return footprint_circle(self.mesh.vertices[:, :2])

    def footprint_radius_m(self) -> float:
        """Radius of :attr:`footprint`."""
        return self.footprint[1]


def footprint_circle(xy: NDArray[np.floating[Any]]) -> tuple[F64, float]:
    """(centre (2,), radius) in metres of a circle holding the (N, 2) points ``xy``: the
    centre of their bounding box, the radius to the farthest."""
    centre: F64 = (xy.min(axis=0) + xy.max(axis=0)) / 2.0
    return centre, float(np.linalg.norm(xy - centre, axis=1).max())


def _sample_image(image: NDArray[np.uint8], st: F32) -> F32:
    """Bilinear lookup of (N, 2) texture coordinates (u right, v up) in an (H, W, 3) image."""
    h, w = image.shape[:2]
    x = np.clip(st[:, 0] * w - 0.5, 0, w - 1)
    y = np.clip((1.0 - st[:, 1]) * h - 0.5, 0, h - 1)
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    img = image.astype(np.float32) / np.float32(255.0)
    top = img[y0, x0] * (1 - fx) + img[y0, x1] * fx
    bottom = img[y1, x0] * (1 - fx) + img[y1, x1] * fx
    out: F32 = (top * (1 - fy) + bottom * fy).astype(np.float32)
    return out


def _solid(a: tuple[float, float, float], b: tuple[float, float, float], seed: int) -> SolidTexture:
    return SolidTexture(a, b, seed=seed, scale=0.6)


def builtin_models() -> list[ObjectModel]:
    """The five procedural classes, in a fixed order; ``drum`` is the symmetric one."""
    crate = merge(
        [
            box((0.32, 0.24, 0.20), (0.0, 0.0, 0.10)),
            box((0.03, 0.03, 0.03), (0.175, -0.07, 0.14)),
            box((0.03, 0.03, 0.03), (0.175, 0.07, 0.14)),
            box((0.03, 0.17, 0.03), (0.205, 0.0, 0.14)),
        ]
    )
    drum = merge(
        [cylinder(0.12, 0.0, 0.34, 48, bottom=True), cylinder(0.09, 0.34, 0.355, 40, bottom=False)]
    )
    l_profile = [
        (-0.16, 0.0),
        (0.16, 0.0),
        (0.16, 0.035),
        (-0.125, 0.035),
        (-0.125, 0.26),
        (-0.16, 0.26),
    ]
    steps = [(-0.15, 0.0), (0.15, 0.0), (0.15, 0.08), (0.05, 0.08), (0.05, 0.16), (-0.05, 0.16)]
    steps += [(-0.05, 0.24), (-0.15, 0.24)]
    wedge = [(-0.18, 0.0), (0.18, 0.0), (0.18, 0.04), (-0.1, 0.2), (-0.18, 0.2)]
    return [
        ObjectModel(
            "l_bracket", extrude(l_profile, 0.14), _solid((0.45, 0.5, 0.58), (0.75, 0.42, 0.2), 101)
        ),
        ObjectModel("crate", crate, _solid((0.78, 0.18, 0.12), (0.45, 0.08, 0.06), 102)),
        ObjectModel(
            "stepped_block", extrude(steps, 0.16), _solid((0.85, 0.7, 0.4), (0.5, 0.32, 0.16), 103)
        ),
        ObjectModel("wedge", extrude(wedge, 0.2), _solid((0.2, 0.62, 0.35), (0.1, 0.4, 0.5), 104)),
        ObjectModel(
            "drum",
            drum,
            _solid((0.15, 0.3, 0.75), (0.08, 0.12, 0.35), 105),
            symmetry={"kind": "continuous", "axis": [0.0, 0.0, 1.0], "origin": [0.0, 0.0, 0.0]},
        ),
    ]


def distractor_model(name: str) -> ObjectModel:
    """An object outside any library: "unknown_box" (34 × 26 × 22 cm carton) or "column"
    (a person-sized cylinder, 16 cm radius, 1.75 m tall). InputError for another name."""
    if name == "unknown_box":
        return ObjectModel(
            name,
            box((0.34, 0.26, 0.22), (0.0, 0.0, 0.11)),
            _solid((0.72, 0.6, 0.42), (0.5, 0.38, 0.24), 201),
        )
    if name == "column":
        return ObjectModel(
            name,
            cylinder(0.16, 0.0, 1.75, 48, bottom=True),
            _solid((0.3, 0.32, 0.36), (0.7, 0.7, 0.72), 202),
        )
    raise InputError(f"unknown distractor {name!r}; choose 'unknown_box' or 'column'")


#: The 18 YCB objects of the shared data set, by kind: flat (lying on the floor), tall,
#: boxes and blocks, cans and round ones.
YCB_OBJECTS: tuple[str, ...] = (
    "adjustable_wrench",
    "extra_large_clamp",
    "large_clamp",
    "hammer",
    "padlock",
    "power_drill",
    "pitcher_base",
    "mustard_bottle",
    "bleach_cleanser",
    "windex_bottle",
    "cracker_box",
    "sugar_box",
    "wood_block",
    "rubiks_cube",
    "master_chef_can",
    "tomato_soup_can",
    "bowl",
    "mug",
)


def ycb_models(folder: Path, names: tuple[str, ...] | list[str]) -> list[ObjectModel]:
    """YCB models ``folder/<name>/textured.obj`` in the order given; InputError naming a
    missing one."""
    return [load_model(folder / name / "textured.obj", name) for name in names]


# YCB classes that are rotationally symmetric about their model z axis (through the xy centre).
_YCB_SYMMETRIC_Z = frozenset({"bowl", "master_chef_can", "tomato_soup_can"})


def load_model(path: Path, name: str | None = None) -> ObjectModel:
    """Load a mesh file (OBJ with UV texture, or PLY etc. with vertex colours) in metres."""
    if not path.is_file():
        raise InputError(f"object model not found: {path}")
    legacy = o3d.io.read_triangle_mesh(path, True)
    if len(legacy.triangles) == 0:
        raise InputError(f"object model has no triangles: {path}")
    mesh = Mesh(np.asarray(legacy.vertices, np.float64), np.asarray(legacy.triangles, np.int32))
    label = name or (path.parent.name if path.stem == "textured" else path.stem)
    symmetry: Symmetry | None = None
    if label in _YCB_SYMMETRIC_Z:
        lo, hi = mesh.vertices.min(0), mesh.vertices.max(0)
        centre = [float((lo[0] + hi[0]) / 2), float((lo[1] + hi[1]) / 2), 0.0]
        symmetry = {"kind": "continuous", "axis": [0.0, 0.0, 1.0], "origin": centre}
    uvs = np.asarray(legacy.triangle_uvs, np.float64)
    if legacy.textures and len(uvs) == 3 * len(mesh.triangles):
        # Open3D hands the texture back bottom-up; flip it to the file's top-down rows so
        # that row = (1 − v)·height holds, as for the image read from disk.
        image = np.asarray(legacy.textures[0])[::-1]
        if image.ndim == 2:
            image = np.repeat(image[:, :, None], 3, axis=2)
        return ObjectModel(
            label,
            mesh,
            uv_texture=np.ascontiguousarray(image[:, :, :3]).astype(np.uint8),
            triangle_uvs=uvs.reshape(-1, 3, 2),
            symmetry=symmetry,
        )
    if legacy.has_vertex_colors():
        colours = np.asarray(legacy.vertex_colors, np.float32)
        return ObjectModel(label, mesh, vertex_colours=colours, symmetry=symmetry)
    seed = sum(label.encode()) % 1000
    return ObjectModel(
        label, mesh, _solid((0.7, 0.7, 0.7), (0.4, 0.4, 0.45), seed), symmetry=symmetry
    )


def write_model_ply(model: ObjectModel, path: Path) -> None:
    """Write the model as a binary PLY (object frame, metres) with vertex colours and normals."""
    legacy = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(model.mesh.vertices),
        o3d.utility.Vector3iVector(model.mesh.triangles),
    )
    legacy.vertex_colors = o3d.utility.Vector3dVector(
        model.colours_at_vertices().astype(np.float64)
    )
    legacy.vertex_normals = o3d.utility.Vector3dVector(model.mesh.vertex_normals)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not o3d.io.write_triangle_mesh(path, legacy, write_ascii=False):
        raise InputError(f"could not write model file {path}")
