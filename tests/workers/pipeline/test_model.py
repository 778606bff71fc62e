"""Library-object preparation: loading, units, sampling, work directory, symmetry."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from workers.pipeline.__main__ import main as pipeline_main
from workers.pipeline.errors import InputError
from workers.pipeline.model import (
    MODEL_PRESETS,
    ModelFileError,
    ModelOptions,
    check_model_header,
    diameter_m,
    load_prepared,
    load_surface,
    prepare_model,
)
from workers.pipeline.model.detect_symmetry import detect_symmetry
from workers.pipeline.model.load import _texture_colors
from workers.pipeline.model.symmetry_group import (
    SymmetrySpec,
    rotation_about,
    spec_from_json,
    spec_to_json,
)

FAST = MODEL_PRESETS["fast"]


def _box_mesh(path: Path, size_xyz: tuple[float, float, float]) -> Path:
    box = o3d.geometry.TriangleMesh.create_box(*size_xyz)
    box.compute_triangle_normals()
    if path.suffix == ".glb":
        _write_glb(path, np.asarray(box.vertices), np.asarray(box.triangles))
    else:
        o3d.io.write_triangle_mesh(path, box)
    return path


def _write_glb(path: Path, vertices: np.ndarray, triangles: np.ndarray) -> None:
    """A minimal binary glTF 2.0 file with one mesh (Open3D 0.20's own .glb writer makes
    files its reader rejects: "Buffer view ... is out of range")."""
    pos = vertices.astype("<f4").tobytes()
    idx = triangles.astype("<u4").tobytes()
    doc = {
        "asset": {"version": "2.0"},
        "buffers": [{"byteLength": len(pos) + len(idx)}],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": len(pos), "target": 34962},
            {"buffer": 0, "byteOffset": len(pos), "byteLength": len(idx), "target": 34963},
        ],
        "accessors": [
            {
                "bufferView": 0,
                "componentType": 5126,
                "count": len(vertices),
                "type": "VEC3",
                "min": vertices.min(axis=0).tolist(),
                "max": vertices.max(axis=0).tolist(),
            },
            {"bufferView": 1, "componentType": 5125, "count": triangles.size, "type": "SCALAR"},
        ],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
        "nodes": [{"mesh": 0}],
        "scenes": [{"nodes": [0]}],
        "scene": 0,
    }
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    binary = pos + idx + b"\0" * (-(len(pos) + len(idx)) % 4)
    chunks = (
        len(text).to_bytes(4, "little")
        + b"JSON"
        + text
        + len(binary).to_bytes(4, "little")
        + b"BIN\0"
        + binary
    )
    header = b"glTF" + (2).to_bytes(4, "little") + (12 + len(chunks)).to_bytes(4, "little")
    path.write_bytes(header + chunks)


def test_diameter_of_a_box_is_its_space_diagonal(tmp_path: Path) -> None:
    # sampled surface points reach the corners only approximately: 1 % tolerance
    pts, _, _ = load_surface(_box_mesh(tmp_path / "b.ply", (0.3, 0.2, 0.1)), ModelOptions())
    assert diameter_m(pts) == pytest.approx(np.sqrt(0.3**2 + 0.2**2 + 0.1**2), rel=0.01)


@pytest.mark.parametrize("suffix", [".ply", ".obj", ".stl", ".glb", ".off"])
def test_every_mesh_format_loads_with_the_same_extent(tmp_path: Path, suffix: str) -> None:
    # the mesh formats, each written by Open3D; 2 % sampling tolerance on the extent
    pts, normals, _ = load_surface(_box_mesh(tmp_path / f"box{suffix}", (0.3, 0.2, 0.1)), FAST)
    assert np.ptp(pts, axis=0) == pytest.approx([0.3, 0.2, 0.1], rel=0.02)
    assert np.linalg.norm(normals, axis=1) == pytest.approx(1.0, abs=1e-6)


@pytest.mark.parametrize("suffix", [".pcd", ".ply"])
def test_point_cloud_files_load_and_get_normals(tmp_path: Path, suffix: str) -> None:
    # a cloud without normals (box surface samples): normals are estimated, unit length
    box = o3d.geometry.TriangleMesh.create_box(0.3, 0.2, 0.1)
    o3d.utility.random.seed(1)
    cloud = box.sample_points_uniformly(5000)
    cloud.normals = o3d.utility.Vector3dVector()
    path = tmp_path / f"cloud{suffix}"
    o3d.io.write_point_cloud(str(path), cloud)
    pts, normals, _ = load_surface(path, FAST)
    assert np.ptp(pts, axis=0) == pytest.approx([0.3, 0.2, 0.1], rel=0.02)
    assert np.linalg.norm(normals, axis=1) == pytest.approx(1.0, abs=1e-6)


@pytest.mark.parametrize(("units", "scale"), [("m", 1.0), ("cm", 100.0), ("mm", 1000.0)])
def test_units_are_converted_to_metres(tmp_path: Path, units: str, scale: float) -> None:
    # the same 1.0 × 0.5 × 0.2 m box written in each unit; 1-2 % sampling tolerance
    mesh = _box_mesh(tmp_path / "box.stl", (1.0 * scale, 0.5 * scale, 0.2 * scale))
    model = prepare_model(mesh, tmp_path / "out", FAST, units=units)
    assert model.diameter_m == pytest.approx(np.sqrt(1.0 + 0.25 + 0.04), rel=0.01)
    assert model.voxel_m == pytest.approx(model.diameter_m / FAST.voxel_divisor)
    assert np.ptp(model.points, axis=0) == pytest.approx([1.0, 0.5, 0.2], rel=0.02)


def test_implausible_size_suggests_wrong_units(tmp_path: Path) -> None:
    mesh = _box_mesh(tmp_path / "box.ply", (1000.0, 500.0, 200.0))  # millimetres
    with pytest.raises(InputError, match="wrong units"):
        prepare_model(mesh, tmp_path / "out", FAST, units="m")


def test_box_symmetry_is_the_dihedral_group_of_eight(tmp_path: Path) -> None:
    # 100 × 50 × 20 box: three 180° turns and the identity; a square prism has eight
    mesh = _box_mesh(tmp_path / "box.ply", (0.1, 0.05, 0.02))
    assert len(prepare_model(mesh, tmp_path / "a").symmetry.rotations) == 4
    square = _box_mesh(tmp_path / "sq.ply", (0.05, 0.05, 0.12))
    assert len(prepare_model(square, tmp_path / "b").symmetry.rotations) == 8


@pytest.mark.parametrize(
    ("content", "suffix", "message"),
    [
        (b"", ".ply", "empty"),
        (b"this is not a mesh\n", ".obj", "no triangles"),
        (b"ply\nformat ascii 1.0\nelement vertex 0\nend_header\n", ".ply", "fewer than 10"),
        (b"solid x\nendsolid x\n", ".stl", "no triangles"),
        (b"abc", ".docx", "unsupported"),
    ],
)
def test_bad_or_empty_files_raise_input_error(
    tmp_path: Path, content: bytes, suffix: str, message: str
) -> None:
    path = tmp_path / f"bad{suffix}"
    path.write_bytes(content)
    with pytest.raises(InputError, match=message):
        prepare_model(path, tmp_path / "out", FAST)
    assert not (tmp_path / "out" / "summary.json").exists()


def test_missing_file_and_bad_units_raise_input_error(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="not found"):
        prepare_model(tmp_path / "nope.obj", tmp_path / "out", FAST)
    mesh = _box_mesh(tmp_path / "box.ply", (1.0, 1.0, 1.0))
    with pytest.raises(InputError, match="units"):
        prepare_model(mesh, tmp_path / "out", FAST, units="inch")


def test_textured_obj_gets_texture_colours_and_work_dir_resumes(
    shared_data: Path, tmp_path: Path
) -> None:
    mesh = shared_data / "ycb" / "power_drill" / "textured.obj"
    model = prepare_model(mesh, tmp_path / "drill")
    assert model.name == "power_drill"
    assert model.colors is not None
    # the drill is mostly dark with a bright teal/yellow body: colours must vary, not be
    # the 0.5 grey that a missing texture gives
    assert model.colors.std(axis=0).min() > 0.05
    assert model.points.shape == model.normals.shape == (6000, 3)
    assert np.allclose(np.linalg.norm(model.normals, axis=1), 1.0, atol=1e-6)
    assert 0.2 < model.diameter_m < 0.3  # a 22 cm drill, in metres
    for name in ("summary.json", "model.ply", "model_down.ply", "features.npy", "fpfh.npy"):
        assert (tmp_path / "drill" / name).is_file()
    assert model.fpfh.shape == (len(model.feature_points), 33)
    stamp = (tmp_path / "drill" / "summary.json").stat().st_mtime_ns
    again = prepare_model(mesh, tmp_path / "drill")
    assert (tmp_path / "drill" / "summary.json").stat().st_mtime_ns == stamp  # not recomputed
    loaded = load_prepared(tmp_path / "drill")
    for m in (again, loaded):
        assert np.allclose(m.points, model.points)
        assert np.allclose(m.fpfh, model.fpfh, atol=1e-4)  # stored as float32
        assert m.diameter_m == model.diameter_m


def test_texture_colours_are_read_the_right_way_up(shared_data: Path) -> None:
    # oracle: the texture file's own pixel at row (1 − v)·height, column u·width
    folder = shared_data / "ycb" / "mustard_bottle"
    mesh = o3d.io.read_triangle_mesh(folder / "textured.obj", True)
    image = np.asarray(o3d.io.read_image(str(folder / "texture_map.png")))
    tri = np.arange(0, len(mesh.triangles), 97)
    bary = np.tile([1.0, 0.0, 0.0], (len(tri), 1))  # at each triangle's first corner
    colours = _texture_colors(mesh, tri, bary)
    assert colours is not None
    uv = np.mod(np.asarray(mesh.triangle_uvs)[3 * tri], 1.0)
    h, w = image.shape[:2]
    rows = np.clip(((1.0 - uv[:, 1]) * h).astype(int), 0, h - 1)
    cols = np.clip((uv[:, 0] * w).astype(int), 0, w - 1)
    expected = image[rows, cols, :3] / 255.0
    # a pixel's rounding may differ at a texel edge; the flipped lookup differs everywhere
    assert np.mean(np.abs(colours - expected).max(axis=1) < 0.02) > 0.95


def test_two_preparations_of_one_model_interleaved_both_finish(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Two workers preparing the same model into one directory: the second finishes while
    the first is about to publish its summary; neither loses its temporary file."""
    mesh = _box_mesh(tmp_path / "box.ply", (0.1, 0.06, 0.04))
    work = tmp_path / "prepared"
    real_replace = Path.replace
    interleaved: list[bool] = []

    def replace_after_the_other(self: Path, target: Path) -> Path:
        if not interleaved:
            interleaved.append(True)
            prepare_model(mesh, work, FAST)  # the other worker, start to finish
        return real_replace(self, target)

    monkeypatch.setattr(Path, "replace", replace_after_the_other)
    prepared = prepare_model(mesh, work, FAST)
    assert interleaved
    assert prepared.diameter_m == pytest.approx(np.linalg.norm([0.1, 0.06, 0.04]), rel=0.05)
    assert not list(work.glob("*.tmp"))
    assert load_prepared(work).diameter_m == prepared.diameter_m


def test_load_prepared_refuses_an_incomplete_directory(tmp_path: Path) -> None:
    with pytest.raises(InputError, match=r"summary\.json"):
        load_prepared(tmp_path)


# ---------------------------------------------------------------- symmetry


@pytest.mark.parametrize(
    ("name", "kind", "n_rotations"),
    [
        ("power_drill", "none", 1),
        ("bowl", "continuous", 1),  # about its axis, no flip: a bowl upside down differs
        ("master_chef_can", "continuous", 2),  # plain cylinder geometry: flip too
        ("tomato_soup_can", "continuous", 2),
        ("wood_block", "discrete", 8),  # square prism: D4
        ("rubiks_cube", "discrete", 24),  # cube geometry: the octahedral group
    ],
)
def test_symmetry_of_ycb_objects(shared_data: Path, name: str, kind: str, n_rotations: int) -> None:
    pts, _, colors = load_surface(shared_data / "ycb" / name / "textured.obj", ModelOptions())
    spec = detect_symmetry(pts, colors)
    assert spec.kind == kind
    assert len(spec.rotations) == n_rotations
    if kind == "continuous":
        assert spec.axis is not None
        assert abs(spec.axis[2]) > 0.99  # YCB cans and bowl stand on the model's z axis
    # every element really maps the surface onto itself (mean NN distance ≪ object size)
    tree = o3d.geometry.KDTreeFlann(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)))
    for s in spec.sample(6)[1:]:
        moved = pts[::20] @ s[:3, :3].T + s[:3, 3]
        d = [np.sqrt(tree.search_knn_vector_3d(p, 1)[2][0]) for p in moved]
        assert float(np.mean(d)) < 0.004
    # labels, grain and coloured faces break the symmetry; the bowl is plain red
    assert spec.appearance_breaks == (kind != "none" and name != "bowl")


def test_symmetry_spec_json_round_trip_and_validation() -> None:
    turn = rotation_about(np.array([0.0, 0.0, 1.0]), np.pi, np.array([0.1, 0.0, 0.0]))
    spec = spec_from_json({"kind": "discrete", "rotations": [turn.tolist()]})
    assert len(spec.rotations) == 2  # identity added first
    assert np.allclose(spec.rotations[0], np.eye(4))
    again = spec_from_json(json.loads(json.dumps(spec_to_json(spec))))
    assert np.allclose(again.rotations[1], turn)
    cont = spec_from_json({"kind": "continuous", "axis": [0, 0, 2], "origin": [0, 0, 0]})
    assert cont.axis is not None and np.allclose(cont.axis, [0, 0, 1])
    assert spec_to_json(SymmetrySpec()) == {"kind": "none", "appearance_breaks": False}
    for bad in (
        {"kind": "spiral"},
        {"kind": "discrete", "rotations": [np.diag([1.0, 1.0, -1.0, 1.0]).tolist()]},
        {"kind": "discrete", "rotations": [[1, 2, 3]]},
        {"kind": "continuous", "axis": [0, 0, 0]},
        "none",
    ):
        with pytest.raises(InputError):
            spec_from_json(bad)


def test_explicit_symmetry_overrides_detection_and_cli_runs(tmp_path: Path) -> None:
    mesh = _box_mesh(tmp_path / "box.ply", (0.1, 0.05, 0.02))
    model = prepare_model(mesh, tmp_path / "out", FAST, symmetry=SymmetrySpec())
    assert model.symmetry.kind == "none"
    assert model.summary["symmetry_source"] == "explicit"
    code = pipeline_main(["model", str(mesh), "--out", str(tmp_path / "cli"), "--units", "m"])
    assert code == 0
    summary = json.loads((tmp_path / "cli" / "summary.json").read_text())
    assert summary["symmetry"]["kind"] == "discrete"
    assert (
        pipeline_main(["model", str(tmp_path / "missing.ply"), "--out", str(tmp_path / "x")]) == 2
    )


# --- hostile model files: counts past the file's size, faces past the vertices ---------------


def _ply(path: Path, header: str, body: bytes) -> Path:
    path.write_bytes(header.encode() + body)
    return path


@pytest.mark.parametrize("fmt", ["binary_little_endian", "ascii"])
def test_ply_declaring_two_billion_vertices_is_a_clear_error(tmp_path: Path, fmt: str) -> None:
    """A 1 kB file must not make the reader allocate for 2 × 10⁹ vertices (48 GB)."""
    header = (
        f"ply\nformat {fmt} 1.0\nelement vertex 2000000000\nproperty float x\n"
        "property float y\nproperty float z\nelement face 1\n"
        "property list uchar int vertex_indices\nend_header\n"
    )
    body = (
        np.zeros((3, 3), "<f4").tobytes() + b"\x03" + np.arange(3, dtype="<i4").tobytes()
        if fmt.startswith("binary")
        else b"0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n"
    )
    path = _ply(tmp_path / "bomb.ply", header, body)
    with pytest.raises(ModelFileError) as err:
        load_surface(path, FAST)
    assert err.value.code == "InvalidModelFile"
    assert "2000000000 vertex elements" in err.value.detail
    assert isinstance(err.value, InputError)


def test_off_declaring_more_vertices_than_it_holds(tmp_path: Path) -> None:
    path = tmp_path / "bomb.off"
    path.write_bytes(b"OFF\n# comment\n2000000000 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    with pytest.raises(ModelFileError, match="2000000000 vertices"):
        load_surface(path, FAST)


def test_face_naming_a_missing_vertex_is_a_clear_error(tmp_path: Path) -> None:
    header = (
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
        "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
    )
    path = _ply(tmp_path / "bad.ply", header, b"0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n")
    with pytest.raises(ModelFileError) as err:
        load_surface(path, FAST)
    assert err.value.code == "InvalidModelFile"
    assert "vertex 7" in err.value.detail and "3 vertices" in err.value.detail


def test_header_check_passes_honest_files(tmp_path: Path) -> None:
    for suffix in (".ply", ".off"):
        path = _box_mesh(tmp_path / f"box{suffix}", (0.1, 0.2, 0.3))
        check_model_header(path)  # no error
        points, _, _ = load_surface(path, FAST)
        assert len(points) > 0
