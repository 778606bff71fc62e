"""Binary glTF 2.0 (``.glb``) of a twin: one node per instance, carrying its library model.

Layout of the scene::

    scene 0
      root node "environment"      matrix GLTF_FROM_ENV (the environment frame, +z up, into
                                   glTF's +y up); extras: environment, snapshot, undrawn
        node "<class>/<instance>"  matrix env_from_object (the pose, unchanged); mesh: the
                                   library model, written once per model and shared

so a node's world transform is ``GLTF_FROM_ENV @ env_from_object``. Units are metres.
Meshes are triangles with normals (and ``COLOR_0`` when the model has colours); a point
cloud model is one ``POINTS`` primitive. Written with NumPy and :mod:`struct` only.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

GLTF_FROM_ENV = np.array(
    [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
)
"""Environment frame (x, y, z; +z up) → glTF (x, z, −y; +y up): a rotation of −90° about x."""

MEDIA_TYPE = "model/gltf-binary"

_ARRAY_BUFFER = 34962
_ELEMENT_ARRAY_BUFFER = 34963
_FLOAT, _UNSIGNED_BYTE, _UNSIGNED_INT = 5126, 5121, 5125
_POINTS, _TRIANGLES = 0, 4


class ModelGeometryError(ValueError):
    """A model whose arrays do not fit together (shapes, indices, non-finite values)."""


@dataclass(frozen=True)
class ModelGeometry:
    """A library model in its own frame (``object``), metres.

    ``positions`` (N, 3); ``normals`` (N, 3) or None (computed for meshes, left out for
    points); ``colors`` (N, 3) in [0, 1] or None; ``triangles`` (F, 3) indices into
    ``positions``, or None for a point cloud (drawn as points)."""

    positions: NDArray[np.float64]
    normals: NDArray[np.float64] | None = None
    colors: NDArray[np.float64] | None = None
    triangles: NDArray[np.int64] | None = None

    def __post_init__(self) -> None:
        n = self.positions.shape[0] if self.positions.ndim == 2 else -1
        if self.positions.shape != (n, 3) or n == 0:
            raise ModelGeometryError(f"positions must be (N>0, 3), got {self.positions.shape}")
        if not np.isfinite(self.positions).all():
            raise ModelGeometryError("positions must be finite")
        for name in ("normals", "colors"):
            value = getattr(self, name)
            if value is not None and value.shape != (n, 3):
                raise ModelGeometryError(f"{name} must be ({n}, 3), got {value.shape}")
        tri = self.triangles
        if tri is not None and (
            tri.ndim != 2
            or tri.shape[1:] != (3,)
            or not tri.size
            or tri.min() < 0
            or tri.max() >= n
        ):
            raise ModelGeometryError(f"triangles must be (F, 3) indices in 0..{n - 1}")


@dataclass(frozen=True)
class SceneNode:
    """One instance: its node ``name``, ``env_from_object`` (4×4, metres), the key of its
    model in the models mapping (None: a node with no mesh) and its ``extras``."""

    name: str
    env_from_object: NDArray[np.float64]
    model: str | None
    extras: dict[str, Any] = field(default_factory=dict)


def write_glb(
    nodes: Sequence[SceneNode],
    models: Mapping[str, ModelGeometry],
    root_extras: dict[str, Any],
    generator: str,
) -> bytes:
    """The ``.glb`` bytes of the scene above. Every model named by a node is written once
    (its mesh shared by the nodes naming it); KeyError for a node naming no model."""
    doc = _Document()
    mesh_of: dict[str, int] = {}
    children: list[int] = []
    for node in nodes:
        entry: dict[str, Any] = {"name": node.name, "extras": node.extras}
        matrix = np.asarray(node.env_from_object, dtype=np.float64)
        if not np.array_equal(matrix, np.eye(4)):
            entry["matrix"] = [float(v) for v in matrix.T.reshape(-1)]  # column-major
        if node.model is not None:
            if node.model not in mesh_of:
                mesh_of[node.model] = doc.add_mesh(node.model, models[node.model])
            entry["mesh"] = mesh_of[node.model]
        children.append(doc.add_node(entry))
    root: dict[str, Any] = {
        "name": "environment",
        "matrix": [float(v) for v in GLTF_FROM_ENV.T.reshape(-1)],
        "extras": root_extras,
    }
    if children:
        root["children"] = children
    doc.json["scenes"] = [{"name": "twin", "nodes": [doc.add_node(root)]}]
    doc.json["scene"] = 0
    doc.json["asset"] = {"version": "2.0", "generator": generator}
    return doc.glb()


def model_glb(name: str, model: ModelGeometry, extras: dict[str, Any], generator: str) -> bytes:
    """The ``.glb`` bytes of one library model in its own frame: one node ``name`` with no
    transform, so vertex coordinates are object-frame metres as they are (+z up as the
    environment, not rotated into glTF's +y up: a client draws it at ``env_from_object``
    inside its own environment-frame scene)."""
    doc = _Document()
    node = doc.add_node({"name": name, "mesh": doc.add_mesh(name, model), "extras": extras})
    doc.json["scenes"] = [{"name": name, "nodes": [node]}]
    doc.json["scene"] = 0
    doc.json["asset"] = {"version": "2.0", "generator": generator}
    return doc.glb()


class _Document:
    """The glTF JSON being built and its binary buffer (every view 4-byte aligned)."""

    def __init__(self) -> None:
        self.json: dict[str, Any] = {}
        self.chunks: list[bytes] = []
        self.length = 0
        self.materials: dict[bool, int] = {}

    def _list(self, name: str, item: dict[str, Any]) -> int:
        items = self.json.setdefault(name, [])
        items.append(item)
        return len(items) - 1

    def add_node(self, node: dict[str, Any]) -> int:
        return self._list("nodes", node)

    def add_view(self, data: bytes, target: int) -> int:
        view = {"buffer": 0, "byteOffset": self.length, "byteLength": len(data), "target": target}
        padded = data + b"\0" * (-len(data) % 4)
        self.chunks.append(padded)
        self.length += len(padded)
        return self._list("bufferViews", view)

    def add_accessor(
        self, array: NDArray[Any], kind: str, component: int, target: int, **extra: Any
    ) -> int:
        view = self.add_view(np.ascontiguousarray(array).tobytes(), target)
        accessor = {
            "bufferView": view,
            "componentType": component,
            "count": int(array.shape[0]),
            "type": kind,
            **extra,
        }
        return self._list("accessors", accessor)

    def material(self, colored: bool) -> int:
        """A matte material: white under vertex colours, light grey without them."""
        if colored not in self.materials:
            factor = [1.0, 1.0, 1.0, 1.0] if colored else [0.8, 0.8, 0.8, 1.0]
            self.materials[colored] = self._list(
                "materials",
                {
                    "name": "vertex colours" if colored else "grey",
                    "pbrMetallicRoughness": {
                        "baseColorFactor": factor,
                        "metallicFactor": 0.0,
                        "roughnessFactor": 1.0,
                    },
                    "doubleSided": True,
                },
            )
        return self.materials[colored]

    def add_mesh(self, name: str, model: ModelGeometry) -> int:
        positions = model.positions.astype(np.float32)
        attributes = {
            "POSITION": self.add_accessor(
                positions,
                "VEC3",
                _FLOAT,
                _ARRAY_BUFFER,
                min=[float(v) for v in positions.min(axis=0)],
                max=[float(v) for v in positions.max(axis=0)],
            )
        }
        normals = model.normals
        if normals is None and model.triangles is not None:
            normals = vertex_normals(model.positions, model.triangles)
        if normals is not None:
            attributes["NORMAL"] = self.add_accessor(
                unit_normals(normals), "VEC3", _FLOAT, _ARRAY_BUFFER
            )
        if model.colors is not None:
            rgba = np.full((len(positions), 4), 255, dtype=np.uint8)
            rgba[:, :3] = np.round(np.clip(model.colors, 0.0, 1.0) * 255.0)
            attributes["COLOR_0"] = self.add_accessor(
                rgba, "VEC4", _UNSIGNED_BYTE, _ARRAY_BUFFER, normalized=True
            )
        primitive: dict[str, Any] = {
            "attributes": attributes,
            "material": self.material(model.colors is not None),
            "mode": _POINTS if model.triangles is None else _TRIANGLES,
        }
        if model.triangles is not None:
            primitive["indices"] = self.add_accessor(
                model.triangles.astype(np.uint32).reshape(-1),
                "SCALAR",
                _UNSIGNED_INT,
                _ELEMENT_ARRAY_BUFFER,
            )
        return self._list("meshes", {"name": name, "primitives": [primitive]})

    def glb(self) -> bytes:
        if self.length:
            self.json["buffers"] = [{"byteLength": self.length}]
        text = json.dumps(self.json, separators=(",", ":"), allow_nan=False).encode()
        text += b" " * (-len(text) % 4)
        body = b"".join(self.chunks)
        chunks = struct.pack("<I4s", len(text), b"JSON") + text
        if body:
            chunks += struct.pack("<I4s", len(body), b"BIN\0") + body
        return struct.pack("<4sII", b"glTF", 2, 12 + len(chunks)) + chunks


def vertex_normals(
    positions: NDArray[np.float64], triangles: NDArray[np.int64]
) -> NDArray[np.float64]:
    """(N, 3) area-weighted vertex normals of a triangle mesh (not yet unit length; a
    vertex in no triangle gets zero)."""
    a, b, c = (positions[triangles[:, i]] for i in range(3))
    face = np.cross(b - a, c - a)  # length 2 × area
    out = np.zeros_like(positions)
    for i in range(3):
        np.add.at(out, triangles[:, i], face)
    return out


def unit_normals(normals: NDArray[np.float64]) -> NDArray[np.float32]:
    """(N, 3) float32 unit vectors; zero or non-finite ones become +z (glTF requires unit
    normals)."""
    n = np.nan_to_num(np.asarray(normals, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    ok = length[:, 0] > 1e-12
    n[ok] /= length[ok]
    n[~ok] = (0.0, 0.0, 1.0)
    return n.astype(np.float32)
