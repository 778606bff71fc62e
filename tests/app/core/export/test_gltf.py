"""The binary glTF writer against independent readers: the Khronos validator (0 errors, 0
warnings) and trimesh (world transforms, vertex positions, shared meshes)."""

from __future__ import annotations

import io
import json
import struct
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from app.core.export.gltf import (
    GLTF_FROM_ENV,
    ModelGeometry,
    ModelGeometryError,
    SceneNode,
    unit_normals,
    vertex_normals,
    write_glb,
)
from tests.app.core.export.validator import assert_valid

GENERATOR = "twindelta test"


def rigid(seed: int) -> np.ndarray:
    """A random env_from_object: a rotation and a translation within ±2 m."""
    rng = np.random.default_rng(seed)
    pose = np.eye(4)
    pose[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    pose[:3, 3] = rng.uniform(-2, 2, 3)
    return pose


def box_model(colors: bool = True) -> ModelGeometry:
    box = trimesh.creation.box(extents=(0.2, 0.1, 0.05))
    n = len(box.vertices)
    return ModelGeometry(
        positions=np.asarray(box.vertices, dtype=np.float64),
        triangles=np.asarray(box.faces, dtype=np.int64),
        colors=np.random.default_rng(1).random((n, 3)) if colors else None,
    )


def cloud_model(n: int = 500) -> ModelGeometry:
    rng = np.random.default_rng(2)
    points = rng.normal(size=(n, 3)) * 0.05
    return ModelGeometry(positions=points, normals=points, colors=rng.random((n, 3)))


def load(data: bytes) -> trimesh.Scene:
    scene = trimesh.load(io.BytesIO(data), file_type="glb", force="scene", process=False)
    assert isinstance(scene, trimesh.Scene)
    return scene


def gltf_json(data: bytes) -> dict:
    magic, version, length = struct.unpack_from("<4sII", data)
    assert (magic, version, length) == (b"glTF", 2, len(data))
    chunk_length, kind = struct.unpack_from("<I4s", data, 12)
    assert kind == b"JSON" and chunk_length % 4 == 0
    return json.loads(data[20 : 20 + chunk_length])


def test_a_mesh_model_is_valid_and_lands_at_conversion_times_pose(tmp_path: Path) -> None:
    model = box_model()
    poses = {f"box/{i}": rigid(i) for i in range(3)}
    data = write_glb(
        [SceneNode(name, pose, "box", {"instance_id": name}) for name, pose in poses.items()],
        {"box": model},
        {"environment": "e"},
        GENERATOR,
    )
    (tmp_path / "mesh.glb").write_bytes(data)
    report = assert_valid(tmp_path / "mesh.glb")
    assert report["info"]["totalTriangleCount"] == len(model.triangles)  # type: ignore[arg-type]

    scene = load(data)
    for name, pose in poses.items():
        world, geometry = scene.graph.get(name)
        np.testing.assert_allclose(world, GLTF_FROM_ENV @ pose, atol=1e-6)
        mesh = scene.geometry[geometry]
        np.testing.assert_allclose(mesh.vertices, model.positions, atol=1e-7)  # float32
        np.testing.assert_array_equal(mesh.faces, model.triangles)
    # one mesh, written once, shared by the three nodes
    doc = gltf_json(data)
    assert len(doc["meshes"]) == 1 and {n.get("mesh") for n in doc["nodes"][:3]} == {0}
    position = doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"]]
    np.testing.assert_allclose(position["min"], model.positions.min(axis=0), atol=1e-7)
    np.testing.assert_allclose(position["max"], model.positions.max(axis=0), atol=1e-7)
    assert doc["asset"] == {"version": "2.0", "generator": GENERATOR}
    assert all(v["byteOffset"] % 4 == 0 and "target" in v for v in doc["bufferViews"])


def test_a_point_cloud_model_is_one_points_primitive(tmp_path: Path) -> None:
    model = cloud_model()
    pose = rigid(7)
    data = write_glb([SceneNode("scan/1", pose, "scan")], {"scan": model}, {}, GENERATOR)
    (tmp_path / "points.glb").write_bytes(data)
    assert_valid(tmp_path / "points.glb")
    doc = gltf_json(data)
    [primitive] = doc["meshes"][0]["primitives"]
    assert primitive["mode"] == 0 and "indices" not in primitive
    assert set(primitive["attributes"]) == {"POSITION", "NORMAL", "COLOR_0"}
    world, geometry = load(data).graph.get("scan/1")
    np.testing.assert_allclose(world, GLTF_FROM_ENV @ pose, atol=1e-6)
    cloud = load(data).geometry[geometry]
    assert isinstance(cloud, trimesh.PointCloud)
    np.testing.assert_allclose(cloud.vertices, model.positions, atol=1e-7)


def test_an_empty_twin_is_a_valid_scene_with_the_root_node_only(tmp_path: Path) -> None:
    data = write_glb([], {}, {"environment": "e", "undrawn": []}, GENERATOR)
    (tmp_path / "empty.glb").write_bytes(data)
    assert_valid(tmp_path / "empty.glb")
    doc = gltf_json(data)
    assert len(data) == 20 + struct.unpack_from("<I", data, 12)[0]  # no BIN chunk
    [root] = doc["nodes"]
    assert root["extras"] == {"environment": "e", "undrawn": []}
    assert "buffers" not in doc and "meshes" not in doc
    matrix = np.array(root["matrix"]).reshape(4, 4).T  # glTF matrices are column-major
    np.testing.assert_array_equal(matrix, GLTF_FROM_ENV)


def test_the_conversion_is_a_proper_rotation_taking_env_z_up_to_gltf_y_up() -> None:
    r = GLTF_FROM_ENV[:3, :3]
    np.testing.assert_array_equal(r @ r.T, np.eye(3))
    assert np.linalg.det(r) == 1.0
    np.testing.assert_array_equal(r @ [0, 0, 1], [0, 1, 0])  # up stays up
    np.testing.assert_array_equal(r @ [0, 1, 0], [0, 0, -1])
    np.testing.assert_array_equal(r @ [1, 0, 0], [1, 0, 0])


def test_computed_normals_are_unit_and_point_out_of_a_closed_mesh() -> None:
    model = box_model(colors=False)
    normals = unit_normals(vertex_normals(model.positions, model.triangles))  # type: ignore[arg-type]
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-6)
    assert (np.einsum("ij,ij->i", normals, model.positions) > 0).all()
    assert unit_normals(np.zeros((2, 3))).tolist() == [[0, 0, 1], [0, 0, 1]]


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"positions": np.zeros((0, 3))}, "positions must be"),
        ({"positions": np.array([[0, 0, np.nan]])}, "finite"),
        ({"positions": np.zeros((3, 3)), "triangles": np.array([[0, 1, 3]])}, "indices in 0..2"),
        ({"positions": np.zeros((3, 3)), "colors": np.zeros((2, 3))}, "colors must be"),
    ],
)
def test_inconsistent_models_are_refused(kwargs: dict, message: str) -> None:
    with pytest.raises(ModelGeometryError, match=message):
        ModelGeometry(**kwargs)
