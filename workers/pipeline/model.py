"""Prepare a library object once: load, convert units, sample, describe, detect symmetry.

``prepare_model(path, work_dir, options, units, symmetry)`` turns a mesh or point-cloud
file (.ply .obj .stl .glb .off .pcd) into a :class:`PreparedModel` — everything pose
estimation needs — and writes it under ``work_dir`` so that later jobs only call
:func:`load_prepared`. All coordinates are in the model's own frame (``object`` frame:
the frame ``env_from_object`` maps from), in metres after unit conversion.

Work-directory layout (version ``FORMAT_VERSION``)::

    work_dir/
      summary.json        name, source sha256, units, options, diameter_m, voxel_m,
                          centre_object, up_object, symmetry spec (and whether detected
                          or explicit), near_symmetries (4×4 lists), point counts, timings;
                          written last, so its presence means the directory is complete
      model.ply           (N, 3) sampled surface cloud with normals and colours (metres)
      model_down.ply      (M, 3) the same cloud voxel-downsampled at ``voxel_m``
      features.npy        (K, 6) float64 points and normals that carry the descriptors: the
                          downsampled cloud, then its part visible from each of
                          ``feature_views`` viewpoints (a scan sees one side; its FPFH
                          must not include the hidden side of a thin object)
      fpfh.npy            (K, 33) float32 FPFH descriptors of ``features.npy``

Re-running with the same source file, units, options and symmetry request returns the
stored result without recomputing it.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from scipy.spatial import ConvexHull, QhullError

from workers.pipeline.errors import InputError
from workers.pipeline.geometry import Points, as_points
from workers.pipeline.symmetry import (
    SymmetryOptions,
    SymmetrySpec,
    detect_symmetry,
    near_symmetries,
    spec_from_json,
    spec_to_json,
)

FORMAT_VERSION = 4  # 4: texture colours read the right way up
UNITS_TO_M: dict[str, float] = {"m": 1.0, "cm": 0.01, "mm": 0.001}
MESH_SUFFIXES = {".ply", ".obj", ".stl", ".glb", ".gltf", ".off"}
CLOUD_SUFFIXES = {".pcd", ".ply", ".xyz", ".pts"}


@dataclass(frozen=True)
class ModelOptions:
    """How a library object is sampled and described.

    ``n_points``: size of the model cloud sampled from a mesh (clouds are thinned to about
    this many points). ``sampling``: ``"poisson"`` (blue-noise sample elimination over a
    5× uniform sample, even spacing) or ``"uniform"`` (area-weighted random). ``voxel_divisor``:
    the feature voxel is ``diameter / voxel_divisor``; FPFH uses a normal radius of
    ``normal_radius_voxels`` and a feature radius of ``feature_radius_voxels`` voxels.
    ``feature_views``: besides whole-model FPFH, descriptors of the part visible from this
    many viewpoints (hidden-point removal) are stored, so that a one-sided scan finds
    matching descriptors. ``seed`` makes sampling reproducible.
    """

    n_points: int = 6000
    sampling: str = "poisson"
    voxel_divisor: float = 25.0
    normal_radius_voxels: float = 2.0
    feature_radius_voxels: float = 5.0
    feature_views: int = 12
    seed: int = 0
    symmetry: SymmetryOptions = field(default_factory=SymmetryOptions)


MODEL_PRESETS: dict[str, ModelOptions] = {
    "default": ModelOptions(),
    "fast": ModelOptions(n_points=3000, sampling="uniform"),
    "fine": ModelOptions(n_points=12000, voxel_divisor=35.0),
}


@dataclass(frozen=True)
class PreparedModel:
    """A library object ready for registration (all in the object frame, metres).

    ``points``/``normals``: (N, 3) float64 surface samples and unit outward normals;
    ``colors``: (N, 3) float64 in [0, 1] or None; ``down_points``/``down_normals``: (M, 3)
    at ``voxel_m``; ``feature_points``/``feature_normals``: (K, 3) points carrying the
    ``fpfh`` (K, 33) descriptors (whole-model and per-view); ``centre_object``: (3,) centroid of the
    samples; ``up_object``: (3,) unit "up" of the object (model +z unless the file says
    otherwise) used to choose among symmetric poses; ``symmetry``: see
    :mod:`workers.pipeline.symmetry`; ``near_symmetries``: 4×4 rotations that almost map
    the object onto itself (tried explicitly by pose estimation).
    """

    name: str
    points: Points
    normals: Points
    colors: Points | None
    down_points: Points
    down_normals: Points
    down_colors: Points | None
    feature_points: Points
    feature_normals: Points
    fpfh: NDArray[np.float64]
    diameter_m: float
    voxel_m: float
    centre_object: NDArray[np.float64]
    up_object: NDArray[np.float64]
    symmetry: SymmetrySpec
    summary: dict[str, Any]
    near_symmetries: tuple[NDArray[np.float64], ...] = ()


# --------------------------------------------------------------------------- loading


class ModelFileError(InputError):
    """A model file whose header promises more than the file holds (element counts past
    its size) or whose faces name vertices it does not have."""

    code = "InvalidModelFile"


# Bytes of one PLY scalar (binary) by type name.
_PLY_SCALAR_BYTES = {
    "char": 1, "uchar": 1, "int8": 1, "uint8": 1,
    "short": 2, "ushort": 2, "int16": 2, "uint16": 2,
    "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4,
    "double": 8, "float64": 8,
}  # fmt: skip
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
    size = path.stat().st_size
    with path.open("rb") as fh:
        head = fh.read(_HEADER_MAX_BYTES)
    if suffix == ".ply":
        body_bytes, needed = _ply_needs(head, size, path.name)
    else:
        body_bytes, needed = _off_needs(head, size, path.name)
    for what, count, at_least in needed:
        if count < 0 or count * at_least > body_bytes:
            raise ModelFileError(
                f"{path.name}: the header declares {count} {what}, which need at least "
                f"{count * at_least} bytes, but the file holds {body_bytes} after its header"
            )


def _ply_needs(head: bytes, size: int, name: str) -> tuple[int, list[tuple[str, int, int]]]:
    end = head.find(b"end_header")
    if not head.startswith(b"ply") or end < 0:
        raise ModelFileError(f"{name}: not a PLY file with a complete header")
    newline = head.find(b"\n", end)
    body_bytes = size - (newline + 1 if newline >= 0 else len(head))
    binary = False
    needed: list[tuple[str, int, int]] = []
    for raw in head[:end].decode("latin-1").splitlines():
        words = raw.split()
        if len(words) >= 2 and words[0] == "format":
            binary = words[1].startswith("binary")
        elif len(words) == 3 and words[0] == "element":
            try:
                count = int(words[2])
            except ValueError:
                raise ModelFileError(f"{name}: element {words[1]!r} has no count") from None
            needed.append((f"{words[1]} elements", count, 0))
        elif len(words) >= 3 and words[0] == "property" and needed:
            what, count, at_least = needed[-1]
            kind = words[2] if words[1] == "list" else words[1]
            if kind not in _PLY_SCALAR_BYTES:
                raise ModelFileError(f"{name}: unknown PLY property type {kind!r}")
            at_least += _PLY_SCALAR_BYTES[kind] if binary else 2
            needed[-1] = (what, count, at_least)
    return body_bytes, needed


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


def _sha256(path: Path) -> str:
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


# --------------------------------------------------------------------------- description


def diameter_m(points: Points) -> float:
    """Largest distance between two of the (N, 3) points (exact, via the convex hull)."""
    p = as_points(points)
    if len(p) < 2:
        return 0.0
    try:
        cand = p[ConvexHull(p).vertices]
    except (QhullError, ValueError):
        cand = p
    if len(cand) > 3000:
        cand = cand[np.random.default_rng(0).choice(len(cand), 3000, replace=False)]
    best = 0.0
    for i in range(0, len(cand), 512):
        d = np.linalg.norm(cand[i : i + 512, None, :] - cand[None, :, :], axis=2)
        best = max(best, float(d.max()))
    return best


def make_cloud(
    points: Points, normals: Points | None, colors: Points | None
) -> o3d.geometry.PointCloud:
    """An Open3D cloud from (N, 3) arrays (normals and colours optional)."""
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(points)))
    if normals is not None:
        pcd.normals = o3d.utility.Vector3dVector(np.ascontiguousarray(normals))
    if colors is not None:
        pcd.colors = o3d.utility.Vector3dVector(np.ascontiguousarray(colors))
    return pcd


def fpfh_features(
    pcd: o3d.geometry.PointCloud,
    voxel_m: float,
    normal_radius_voxels: float,
    feature_radius_voxels: float,
) -> NDArray[np.float64]:
    """(M, 33) FPFH of a downsampled cloud; estimates normals (keeping orientation) if absent."""
    if not pcd.has_normals():
        pcd.estimate_normals(
            o3d.geometry.KDTreeSearchParamHybrid(radius=normal_radius_voxels * voxel_m, max_nn=30)
        )
    # no ``indices``: Open3D's default computes every point ([] would compute none)
    feat = o3d.pipelines.registration.compute_fpfh_feature(  # type: ignore[call-arg]
        pcd,
        o3d.geometry.KDTreeSearchParamHybrid(radius=feature_radius_voxels * voxel_m, max_nn=100),
    )
    return np.asarray(feat.data, dtype=np.float64).T.copy()


def view_features(
    points: Points,
    normals: Points,
    down_points: Points,
    down_normals: Points,
    voxel_m: float,
    options: ModelOptions,
) -> tuple[Points, Points, NDArray[np.float64]]:
    """Descriptor-carrying points: (K, 3) points, (K, 3) normals, (K, 33) FPFH.

    The whole downsampled model first, then for each of ``options.feature_views``
    viewpoints (Fibonacci sphere at three diameters) the visible part of the dense cloud
    (hidden-point removal), downsampled at ``voxel_m`` with its own FPFH.
    """
    nr, fr = options.normal_radius_voxels, options.feature_radius_voxels
    pts = [down_points]
    nrm = [down_normals]
    feats = [fpfh_features(make_cloud(down_points, down_normals, None), voxel_m, nr, fr)]
    n = options.feature_views
    if n > 0:
        centre = points.mean(axis=0)
        diam = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
        i = np.arange(n) + 0.5
        z = 1.0 - 2.0 * i / n
        phi = np.pi * (1 + 5**0.5) * i
        dirs = np.stack(
            [np.sqrt(1 - z**2) * np.cos(phi), np.sqrt(1 - z**2) * np.sin(phi), z], axis=1
        )
        dense = make_cloud(points, normals, None)
        for d in dirs:
            _, idx = dense.hidden_point_removal(centre + 3.0 * diam * d, 300.0 * diam)
            vis = np.asarray(idx, dtype=np.int64)
            if len(vis) < 20:
                continue
            vp, vn, _ = _downsample(points[vis], normals[vis], None, voxel_m)
            if len(vp) < 10:
                continue
            pts.append(vp)
            nrm.append(vn)
            feats.append(fpfh_features(make_cloud(vp, vn, None), voxel_m, nr, fr))
    return np.vstack(pts), np.vstack(nrm), np.vstack(feats)


def _downsample(
    points: Points, normals: Points, colors: Points | None, voxel_m: float
) -> tuple[Points, Points, Points | None]:
    down = make_cloud(points, normals, colors).voxel_down_sample(voxel_m)
    nrm = np.asarray(down.normals)
    nrm = nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    return (
        np.asarray(down.points).copy(),
        nrm,
        np.asarray(down.colors).copy() if colors is not None else None,
    )


# --------------------------------------------------------------------------- prepare / load


def _request_key(sha: str, units: str, options: ModelOptions, symmetry: SymmetrySpec | None) -> str:
    blob = json.dumps(
        {
            "v": FORMAT_VERSION,
            "sha": sha,
            "units": units,
            "options": asdict(options),
            "symmetry": None if symmetry is None else spec_to_json(symmetry),
        },
        sort_keys=True,
    )
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def prepare_model(
    path: Path,
    work_dir: Path,
    options: ModelOptions = MODEL_PRESETS["default"],
    units: str = "m",
    symmetry: SymmetrySpec | None = None,
    name: str | None = None,
) -> PreparedModel:
    """Load ``path`` (units ``units``), sample, describe and save it under ``work_dir``.

    ``symmetry`` None means detect it; an explicit spec is validated and kept. Returns the
    prepared model (object frame, metres). Resumes: when ``work_dir/summary.json`` was
    written for the same file, units, options and symmetry request, loads it instead.
    Raises InputError for unusable files, units or symmetry specs.
    """
    path = Path(path)
    work_dir = Path(work_dir)
    if not path.is_file():
        raise InputError(f"{path.name}: model file not found")
    sha = _sha256(path)
    key = _request_key(sha, units, options, symmetry)
    summary_path = work_dir / "summary.json"
    if summary_path.is_file():
        try:
            if json.loads(summary_path.read_text()).get("request_key") == key:
                return load_prepared(work_dir)
        except (ValueError, InputError):
            pass
    t0 = time.perf_counter()
    points, normals, colors = load_surface(path, options, units)
    t_load = time.perf_counter() - t0
    diam = diameter_m(points)
    if not np.isfinite(diam) or diam <= 1e-6:
        raise InputError(f"{path.name}: the model has no extent (diameter {diam:g} m)")
    if diam > 100.0:
        raise InputError(
            f"{path.name}: diameter {diam:g} m after conversion from {units!r} — wrong units?"
        )
    voxel = diam / options.voxel_divisor
    t1 = time.perf_counter()
    d_pts, d_nrm, d_col = _downsample(points, normals, colors, voxel)
    f_pts, f_nrm, fpfh = view_features(points, normals, d_pts, d_nrm, voxel, options)
    t_feat = time.perf_counter() - t1
    t2 = time.perf_counter()
    spec = symmetry if symmetry is not None else detect_symmetry(points, colors, options.symmetry)
    near = near_symmetries(points, spec, options.symmetry)
    t_sym = time.perf_counter() - t2
    centre = points.mean(axis=0)
    up = np.array([0.0, 0.0, 1.0])
    summary: dict[str, Any] = {
        "format_version": FORMAT_VERSION,
        "request_key": key,
        "name": name or (path.parent.name if path.stem == "textured" else path.stem),
        "source": path.name,
        "source_sha256": sha,
        "units": units,
        "options": asdict(options),
        "diameter_m": diam,
        "voxel_m": voxel,
        "centre_object": centre.tolist(),
        "up_object": up.tolist(),
        "n_points": len(points),
        "n_down": len(d_pts),
        "n_features": len(f_pts),
        "has_colors": colors is not None,
        "symmetry": spec_to_json(spec),
        "near_symmetries": [np.round(m, 9).tolist() for m in near],
        "symmetry_source": "explicit" if symmetry is not None else "detected",
        "timings_s": {"load_sample": t_load, "features": t_feat, "symmetry": t_sym},
    }
    work_dir.mkdir(parents=True, exist_ok=True)
    o3d.io.write_point_cloud(work_dir / "model.ply", make_cloud(points, normals, colors))
    o3d.io.write_point_cloud(work_dir / "model_down.ply", make_cloud(d_pts, d_nrm, d_col))
    np.save(work_dir / "features.npy", np.hstack([f_pts, f_nrm]))
    np.save(work_dir / "fpfh.npy", fpfh.astype(np.float32))
    tmp = summary_path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(summary, indent=2))
    tmp.replace(summary_path)  # written last: its presence means the directory is complete
    return load_prepared(work_dir)


def load_prepared(work_dir: Path) -> PreparedModel:
    """Load a model written by :func:`prepare_model`; InputError if incomplete or stale."""
    work_dir = Path(work_dir)
    summary_path = work_dir / "summary.json"
    if not summary_path.is_file():
        raise InputError(f"{work_dir}: no prepared model (summary.json missing)")
    try:
        summary = json.loads(summary_path.read_text())
    except ValueError as exc:
        raise InputError(f"{summary_path}: unreadable summary ({exc})") from exc
    if summary.get("format_version") != FORMAT_VERSION:
        raise InputError(f"{work_dir}: prepared with format {summary.get('format_version')}")
    full = o3d.io.read_point_cloud(work_dir / "model.ply")
    down = o3d.io.read_point_cloud(work_dir / "model_down.ply")
    fpfh_path = work_dir / "fpfh.npy"
    feat_path = work_dir / "features.npy"
    if (
        len(full.points) == 0
        or len(down.points) == 0
        or not fpfh_path.is_file()
        or not feat_path.is_file()
    ):
        raise InputError(f"{work_dir}: prepared model files are missing or empty")
    fpfh = np.load(fpfh_path).astype(np.float64)
    feat = np.load(feat_path).astype(np.float64)
    if feat.ndim != 2 or feat.shape[1] != 6 or fpfh.shape != (len(feat), 33):
        raise InputError(
            f"{work_dir}: features.npy {feat.shape} and fpfh.npy {fpfh.shape} disagree"
        )
    has_col = bool(summary.get("has_colors"))
    return PreparedModel(
        name=str(summary["name"]),
        points=np.asarray(full.points).copy(),
        normals=np.asarray(full.normals).copy(),
        colors=np.asarray(full.colors).copy() if has_col else None,
        down_points=np.asarray(down.points).copy(),
        down_normals=np.asarray(down.normals).copy(),
        down_colors=np.asarray(down.colors).copy() if has_col else None,
        feature_points=feat[:, :3].copy(),
        feature_normals=feat[:, 3:].copy(),
        fpfh=fpfh,
        diameter_m=float(summary["diameter_m"]),
        voxel_m=float(summary["voxel_m"]),
        centre_object=np.asarray(summary["centre_object"], dtype=np.float64),
        up_object=np.asarray(summary["up_object"], dtype=np.float64),
        symmetry=spec_from_json(summary["symmetry"]),
        near_symmetries=tuple(
            np.asarray(m, dtype=np.float64) for m in summary.get("near_symmetries", [])
        ),
        summary=summary,
    )


def with_symmetry(model: PreparedModel, spec: SymmetrySpec) -> PreparedModel:
    """The same prepared model with another symmetry spec (not written to disk)."""
    return replace(model, symmetry=spec)


# --------------------------------------------------------------------------- CLI


def cli(argv: list[str]) -> int:
    """``python -m workers.pipeline model MESH --out DIR [--units mm] [--symmetry JSON]``."""
    ap = argparse.ArgumentParser(prog="python -m workers.pipeline model")
    ap.add_argument("mesh", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--units", default="m", choices=sorted(UNITS_TO_M))
    ap.add_argument("--preset", default="default", choices=sorted(MODEL_PRESETS))
    ap.add_argument("--name", default=None)
    ap.add_argument("--symmetry", default="auto", help='"auto", "none" or a JSON spec')
    args = ap.parse_args(argv)
    spec: SymmetrySpec | None = None
    if args.symmetry != "auto":
        raw: Any = {"kind": "none"} if args.symmetry == "none" else json.loads(args.symmetry)
        spec = spec_from_json(raw)
    try:
        model = prepare_model(
            args.mesh, args.out, MODEL_PRESETS[args.preset], args.units, spec, name=args.name
        )
    except InputError as exc:
        print(exc)
        return 2
    s = dict(model.summary)
    s.pop("options", None)
    print(json.dumps(s, indent=2))
    return 0
