"""The NumPy PLY reader against files written by Open3D and by hand: binary (both byte
orders) and ASCII, meshes with polygons, clouds read in chunks, and broken files."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from app.core.export.ply import PlyError, colors_of, iter_vertices, positions_of, read_model

ASCII_QUAD = b"""ply
format ascii 1.0
comment a unit square as one quad, with a lone triangle after it
element vertex 5
property float x
property float y
property float z
property uchar red
property uchar green
property uchar blue
element face 2
property list uchar int vertex_indices
end_header
0 0 0 255 0 0
1 0 0 0 255 0
1 1 0 0 0 255
0 1 0 255 255 255
0 0 1 0 0 0
4 0 1 2 3
3 0 1 4
"""


def test_an_open3d_mesh_reads_back_with_normals_colours_and_faces(tmp_path: Path) -> None:
    mesh = o3d.geometry.TriangleMesh.create_box(0.2, 0.1, 0.05)
    mesh.compute_vertex_normals()
    colors = np.random.default_rng(0).integers(0, 256, (8, 3)) / 255.0
    mesh.vertex_colors = o3d.utility.Vector3dVector(colors)
    o3d.io.write_triangle_mesh(str(tmp_path / "box.ply"), mesh)
    model = read_model(tmp_path / "box.ply")
    np.testing.assert_array_equal(model.positions, np.asarray(mesh.vertices))
    np.testing.assert_array_equal(model.triangles, np.asarray(mesh.triangles))
    np.testing.assert_allclose(model.normals, np.asarray(mesh.vertex_normals))  # type: ignore[arg-type]
    np.testing.assert_allclose(model.colors, colors)  # type: ignore[arg-type]


def test_ascii_polygons_are_fanned_into_triangles(tmp_path: Path) -> None:
    (tmp_path / "quad.ply").write_bytes(ASCII_QUAD)
    model = read_model(tmp_path / "quad.ply")
    assert model.triangles.tolist() == [[0, 1, 2], [0, 2, 3], [0, 1, 4]]  # type: ignore[union-attr]
    assert model.colors[0].tolist() == [1.0, 0.0, 0.0]  # type: ignore[index]
    assert model.normals is None and model.positions.shape == (5, 3)


def test_big_endian_clouds_with_16_bit_colours(tmp_path: Path) -> None:
    header = (
        b"ply\nformat binary_big_endian 1.0\nelement vertex 2\nproperty double x\n"
        b"property double y\nproperty double z\nproperty ushort red\nproperty ushort green\n"
        b"property ushort blue\nend_header\n"
    )
    body = struct.pack(">dddHHH", 1.5, -2.0, 3.25, 65535, 0, 32768)
    body += struct.pack(">dddHHH", 0.0, 0.0, 0.0, 0, 65535, 0)
    (tmp_path / "be.ply").write_bytes(header + body)
    model = read_model(tmp_path / "be.ply")
    assert model.triangles is None
    assert model.positions.tolist() == [[1.5, -2.0, 3.25], [0.0, 0.0, 0.0]]
    np.testing.assert_allclose(model.colors[0], [1.0, 0.0, 32768 / 65535])  # type: ignore[index]


def test_a_cloud_is_read_in_chunks_of_the_size_asked(tmp_path: Path) -> None:
    points = np.random.default_rng(1).random((1003, 3))
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    o3d.io.write_point_cloud(str(tmp_path / "c.ply"), cloud)
    chunks = list(iter_vertices(tmp_path / "c.ply", chunk=100))
    assert [len(c) for c in chunks] == [100] * 10 + [3]
    np.testing.assert_array_equal(np.concatenate([positions_of(c) for c in chunks]), points)
    assert colors_of(chunks[0]) is None


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"solid x\n", "not a PLY file"),
        (b"ply\nformat binary_little_endian 1.0\nelement vertex 1000\nproperty float x\n"
         b"property float y\nproperty float z\nend_header\n" + b"\0" * 12, "declares 1000"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
         b"end_header\n0 0\n", "no vertex element with x, y and z"),
        (b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
         b"property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
         b"end_header\n0 0 0\n1 0 0\n3 0 1 7\n", "outside 0..1"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
         b"property float z\nend_header\n0 zero 0\n", "not 3 numbers"),
    ],
)  # fmt: skip
def test_broken_files_are_a_ply_error_naming_the_problem(
    tmp_path: Path, content: bytes, message: str
) -> None:
    (tmp_path / "bad.ply").write_bytes(content)
    with pytest.raises(PlyError, match=message):
        read_model(tmp_path / "bad.ply")
