"""Read a library object's mesh or cloud file: header checks, mesh sampling, texture colours."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from app.formats import FormatError
from app.formats.ply import read_ply_file_header
from workers.pipeline.errors import InputError
from workers.pipeline.geometry import Points
from workers.pipeline.model.options import UNITS_TO_M, ModelOptions

MESH_SUFFIXES = {".ply", ".obj", ".stl", ".glb", ".gltf", ".off"}
CLOUD_SUFFIXES = {".pcd", ".ply", ".xyz", ".pts"}


class ModelFileError(InputError):
    """A model file whose header promises more than the file holds (element counts past
    its size) or whose faces name vertices it does not have."""

    code = "InvalidModelFile"


_HEADER_MAX_BYTES = 64 * 1024


def check_model_header(path: Path) -> None:
    """Check the element counts a PLY or OFF header declares against the file's size before
    any reader allocates for them (a 1 kB file declaring 2 × 10⁹ vertices would otherwise
    end in ``bad_alloc`` or the OOM killer). Each element needs at least its binary size
    (a list at least its count) or, in ASCII, two characters per value. Raises
    :class:`ModelFileError`; other formats pass."""
    suffix = path.suffix.lower()
    if suffix not in {".ply", ".off"}:
        return
    if suffix == ".ply":
        try:
            read_ply_file_header(path)
        except FormatError as exc:
            raise ModelFileError(exc.detail) from exc
        return
    size = path.stat().st_size
    with path.open("rb") as fh:
        head = fh.read(_HEADER_MAX_BYTES)
    body_bytes, needed = _off_needs(head, size, path.name)
    for what, count, at_least in needed:
        if count < 0 or count * at_least > body_bytes:
            raise ModelFileError(
                f"{path.name}: the header declares {count} {what}, which need at least "
                f"{count * at_least} bytes, but the file holds {body_bytes} after its header"
            )


def _off_needs(head: bytes, size: int, name: str) -> tuple[int, list[tuple[str, int, int]]]:
    consumed = 0
    words: list[bytes] = []
    for line in head.split(b"\n")[:-1]:  # complete lines; comments and blanks may come first
        consumed += len(line) + 1
        words += line.split(b"#", 1)[0].split()
        if words and words[0].endswith(b"OFF"):
            words = words[1:]  # the keyword; the counts may follow on the same line
        if len(words) >= 2:
            break
    try:
        n_vertices, n_faces = int(words[0]), int(words[1])
    except (IndexError, ValueError):
        raise ModelFileError(f"{name}: an OFF header needs vertex and face counts") from None
    # ASCII: a vertex is at least three numbers ("0 0 0\n"), a face at least its count
    return size - consumed, [("vertices", n_vertices, 6), ("faces", n_faces, 2)]


def _check_faces(mesh: o3d.geometry.TriangleMesh, name: str) -> None:
    """Every face names vertices the mesh has (no index out of range)."""
    faces = np.asarray(mesh.triangles)
    n_vertices = len(mesh.vertices)
    bad = faces[(faces < 0) | (faces >= n_vertices)]
    if bad.size:
        raise ModelFileError(
            f"{name}: a face names vertex {int(bad[0])}, but the file has {n_vertices} "
            f"vertices (0..{n_vertices - 1})"
        )


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _texture_colors(
    mesh: o3d.geometry.TriangleMesh, tri: NDArray[np.int64], bary: NDArray[np.float64]
) -> NDArray[np.float64] | None:
    """Colours (K, 3) in [0, 1] at barycentric points of triangles ``tri`` via the UVs."""
    if not (mesh.has_triangle_uvs() and len(mesh.textures) > 0):
        return None
    uvs = np.asarray(mesh.triangle_uvs, dtype=np.float64)
    if uvs.shape[0] != 3 * len(mesh.triangles):
        return None
    uv = (
        uvs[3 * tri] * bary[:, :1]
        + uvs[3 * tri + 1] * bary[:, 1:2]
        + uvs[3 * tri + 2] * bary[:, 2:]
    )
    mat_ids = np.asarray(mesh.triangle_material_ids, dtype=np.int64)
    mat = mat_ids[tri] if mat_ids.shape[0] == len(mesh.triangles) else np.zeros(len(tri), np.int64)
    out = np.full((len(tri), 3), 0.5)
    for m_id in np.unique(mat):
        if m_id < 0 or m_id >= len(mesh.textures):
            continue
        img = np.asarray(mesh.textures[int(m_id)])
        if img.ndim != 3 or img.shape[0] == 0:
            continue
        h, w = img.shape[:2]
        sel = mat == m_id
        u = np.mod(uv[sel, 0], 1.0)
        v = np.mod(uv[sel, 1], 1.0)
        col = np.clip((u * w).astype(np.int64), 0, w - 1)
        # Open3D hands the texture back bottom-up (row 0 is the file's last row; checked
        # against the PNG), so the file's row (1 − v)·h is this array's row v·h
        row = np.clip((v * h).astype(np.int64), 0, h - 1)
        pix = img[row, col, :3].astype(np.float64)
        out[sel] = pix / (
            65535.0 if img.dtype == np.uint16 else 255.0 if img.dtype == np.uint8 else 1.0
        )
    return out


def _sample_mesh(
    mesh: o3d.geometry.TriangleMesh, options: ModelOptions
) -> tuple[Points, Points, Points | None]:
    """Area-weighted surface samples with face normals and texture/vertex colours."""
    v = np.asarray(mesh.vertices, dtype=np.float64)
    f = np.asarray(mesh.triangles, dtype=np.int64)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    cross = np.cross(b - a, c - a)
    area2 = np.linalg.norm(cross, axis=1)
    if not np.isfinite(area2).all() or area2.sum() <= 0:
        raise InputError("the mesh has no surface area (degenerate or empty triangles)")
    rng = np.random.default_rng(options.seed)
    n_init = options.n_points * (5 if options.sampling == "poisson" else 1)
    tri = rng.choice(len(f), size=n_init, p=area2 / area2.sum())
    r1 = np.sqrt(rng.random(n_init))
    r2 = rng.random(n_init)
    bary = np.stack([1 - r1, r1 * (1 - r2), r1 * r2], axis=1)
    pts = a[tri] * bary[:, :1] + b[tri] * bary[:, 1:2] + c[tri] * bary[:, 2:]
    face_n = cross / np.maximum(area2, 1e-30)[:, None]
    nrm = face_n[tri]
    colors = _texture_colors(mesh, tri, bary)
    if colors is None and mesh.has_vertex_colors():
        vc = np.asarray(mesh.vertex_colors, dtype=np.float64)
        colors = (
            vc[f[tri, 0]] * bary[:, :1] + vc[f[tri, 1]] * bary[:, 1:2] + vc[f[tri, 2]] * bary[:, 2:]
        )
    if options.sampling == "poisson":
        init = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        init.normals = o3d.utility.Vector3dVector(nrm)
        if colors is not None:
            init.colors = o3d.utility.Vector3dVector(colors)
        out = mesh.sample_points_poisson_disk(options.n_points, pcl=init)
        pts = np.asarray(out.points).copy()
        nrm = np.asarray(out.normals).copy()
        colors = np.asarray(out.colors).copy() if colors is not None else None
    return pts, nrm, colors


def _orient_outward(pcd: o3d.geometry.PointCloud) -> None:
    """Flip normals so that they point away from the cloud's centroid (in place)."""
    pts = np.asarray(pcd.points)
    nrm = np.asarray(pcd.normals)
    flip = np.einsum("ij,ij->i", nrm, pts - pts.mean(axis=0)) < 0
    nrm[flip] *= -1.0
    pcd.normals = o3d.utility.Vector3dVector(nrm)


def load_surface(
    path: Path, options: ModelOptions, units: str = "m"
) -> tuple[Points, Points, Points | None]:
    """Load a mesh or cloud file and return (points, normals, colours or None) in metres.

    Meshes are sampled (``options.sampling``); clouds are thinned to about
    ``options.n_points`` and get normals (estimated and oriented away from the centroid when
    the file has none). Raises InputError for unknown units or suffix, unreadable, empty or
    non-finite files.
    """
    if units not in UNITS_TO_M:
        raise InputError(f"units must be one of {sorted(UNITS_TO_M)}, got {units!r}")
    scale = UNITS_TO_M[units]
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES | CLOUD_SUFFIXES:
        raise InputError(f"{path.name}: unsupported model format {suffix!r}")
    if not path.is_file() or path.stat().st_size == 0:
        raise InputError(f"{path.name}: file is missing or empty")
    check_model_header(path)
    mesh: o3d.geometry.TriangleMesh | None = None
    if suffix in MESH_SUFFIXES:
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            mesh = o3d.io.read_triangle_mesh(path, True)
        if len(mesh.triangles) == 0:
            mesh = None
        else:
            _check_faces(mesh, path.name)
    if mesh is not None:
        mesh.scale(scale, center=np.zeros(3))
        v = np.asarray(mesh.vertices)
        if not np.isfinite(v).all():
            raise InputError(f"{path.name}: mesh has non-finite vertices")
        return _sample_mesh(mesh, options)
    if suffix not in CLOUD_SUFFIXES:
        raise InputError(f"{path.name}: no triangles could be read from this mesh file")
    pcd = o3d.io.read_point_cloud(path)
    pcd = pcd.remove_non_finite_points()
    if len(pcd.points) < 10:
        raise InputError(f"{path.name}: fewer than 10 finite points could be read")
    pcd.scale(scale, center=np.zeros(3))
    pts = np.asarray(pcd.points)
    ext = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
    if ext <= 0:
        raise InputError(f"{path.name}: all points coincide")
    if len(pcd.points) > options.n_points:
        # thin to roughly n_points with a voxel grid sized from the current density
        voxel = ext / np.sqrt(options.n_points) / 2.0
        for _ in range(20):
            down = pcd.voxel_down_sample(voxel)
            if len(down.points) <= options.n_points * 1.2:
                break
            voxel *= 1.25
        pcd = down
    if not pcd.has_normals():
        pts = np.asarray(pcd.points)
        spacing = ext / np.sqrt(max(len(pts), 1))
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=4 * spacing, max_nn=30))
        _orient_outward(pcd)
    nrm = np.asarray(pcd.normals).copy()
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    colors = np.asarray(pcd.colors).copy() if pcd.has_colors() else None
    return np.asarray(pcd.points).copy(), nrm, colors
