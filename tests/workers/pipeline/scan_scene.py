"""A synthetic laser scan of a generated room: the floor around the marker sheet sampled
every 2 mm with the floor texture and the printed markers, the walls and two boxes every
2 cm, all coloured, then moved by a known rigid ``scan_from_env`` (a scanner's own frame)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import laspy
import numpy as np
import open3d as o3d
import pye57
from numpy.typing import NDArray
from pyquaternion import Quaternion

from workers.pipeline.geometry import Mat4, make_rigid, rotation_from_rotvec, transform_points
from workers.pipeline.synth.markers import MarkerSheet, marker_sheet
from workers.pipeline.synth.options import RoomOptions
from workers.pipeline.synth.scene import room_surfaces
from workers.pipeline.synth.shapes import box


@dataclass(frozen=True)
class SyntheticScan:
    points_scan: NDArray[np.float64]  # (N, 3) metres, scanner frame
    colors: NDArray[np.uint8]  # (N, 3) RGB
    scan_from_env: Mat4
    sheet: MarkerSheet


def _floor_patch(
    sheet: MarkerSheet, spacing_m: float, rng: np.random.Generator, printed: bool
) -> tuple[NDArray[np.float64], NDArray[np.float32]]:
    """Floor points z = 0 on a jittered grid around the markers, with their colours."""
    reach = max(np.linalg.norm(p[:2, 3]) for p in sheet.env_from_marker.values())
    half = reach + sheet.tile_radius_m() + 0.05
    axis = np.arange(-half, half, spacing_m)
    xx, yy = np.meshgrid(axis, axis, indexing="ij")
    pts = np.column_stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)])
    pts[:, :2] += rng.uniform(-0.25, 0.25, (len(pts), 2)) * spacing_m
    pts[:, 2] += rng.normal(0.0, 0.0003, len(pts))  # 0.3 mm range noise
    floor = next(s for s in room_surfaces(RoomOptions()) if s.name == "floor")
    colors = floor.texture.colours(pts.astype(np.float32))
    if printed:
        grey, on_paper = sheet.albedo(pts.astype(np.float32))
        colors[on_paper] = grey[on_paper, None]
    return pts, colors


def _sample_mesh(
    vertices: NDArray[np.float64],
    triangles: NDArray[np.int32],
    spacing_m: float,
    rng: np.random.Generator,
    inside_only: bool = False,
) -> NDArray[np.float64]:
    """Points uniformly on the triangles, ``spacing_m`` apart on average."""
    a, b, c = (vertices[triangles[:, k]] for k in range(3))
    normal = np.cross(b - a, c - a)
    area = 0.5 * np.linalg.norm(normal, axis=1)
    if inside_only:  # the faces a scanner in the room sees: turned towards (0, 0, 1)
        area[np.sum(normal * ((a + b + c) / 3 - [0.0, 0.0, 1.0]), axis=1) > 0] = 0.0
    n = rng.poisson(area / spacing_m**2)
    tri = np.repeat(np.arange(len(triangles)), n)
    r1, r2 = rng.random(len(tri)), rng.random(len(tri))
    s = np.sqrt(r1)
    return (1 - s)[:, None] * a[tri] + (s * (1 - r2))[:, None] * b[tri] + (s * r2)[:, None] * c[tri]


def synthetic_scan(
    seed: int = 0, floor_spacing_m: float = 0.002, printed: bool = True
) -> SyntheticScan:
    """The scan (``printed`` False: the floor without the sheet's print)."""
    rng = np.random.default_rng(seed)
    room = RoomOptions()
    sheet = marker_sheet(room)
    floor_pts, floor_cols = _floor_patch(sheet, floor_spacing_m, rng, printed)
    parts, cols = [floor_pts], [floor_cols]
    for surface in room_surfaces(room):
        if surface.name == "floor":
            continue
        pts = _sample_mesh(surface.mesh.vertices, surface.mesh.triangles, 0.02, rng, True)
        parts.append(pts)
        cols.append(surface.texture.colours(pts.astype(np.float32)))
    for centre in ((1.6, 0.3, 0.2), (-1.4, -1.5, 0.15)):
        mesh = box((0.3, 0.4, 2 * centre[2]), centre)
        pts = _sample_mesh(mesh.vertices, mesh.triangles, 0.01, rng)
        parts.append(pts)
        cols.append(np.tile(np.asarray([[0.8, 0.2, 0.1]], np.float32), (len(pts), 1)))
    points_env = np.concatenate(parts)
    colors = np.clip(np.rint(np.concatenate(cols) * 255.0), 0, 255).astype(np.uint8)
    scan_from_env = make_rigid(rotation_from_rotvec(rng.normal(0, 1.0, 3)), rng.uniform(-3, 3, 3))
    return SyntheticScan(transform_points(scan_from_env, points_env), colors, scan_from_env, sheet)


# --- tiny scan files, written by independent writers (pye57, laspy, Open3D) ------------------


def cloud(n: int = 500, seed: int = 0) -> tuple[NDArray[np.float64], NDArray[np.uint8]]:
    """(n, 3) points in a 2 m cube and (n, 3) uint8 colours."""
    rng = np.random.default_rng(seed)
    return rng.uniform(-1.0, 1.0, (n, 3)), rng.integers(0, 256, (n, 3), dtype=np.uint8)


def write_e57(
    path: Path,
    scans: list[tuple[NDArray[np.float64], NDArray[np.uint8] | None, Mat4]],
) -> None:
    """An E57 file of several scans, each (points in its scanner frame, colours or None,
    ``common_from_scanner`` pose, stored as the scan's quaternion and translation)."""
    with pye57.E57(str(path), mode="w") as e57:
        for points, colors, pose in scans:
            data: dict[str, NDArray[Any]] = {
                "cartesianX": points[:, 0].copy(),
                "cartesianY": points[:, 1].copy(),
                "cartesianZ": points[:, 2].copy(),
            }
            if colors is not None:
                for k, name in enumerate(("colorRed", "colorGreen", "colorBlue")):
                    data[name] = colors[:, k].copy()
            quaternion = Quaternion(matrix=pose[:3, :3], atol=1e-6).elements
            e57.write_scan_raw(data, rotation=quaternion, translation=pose[:3, 3].copy())


def write_las(
    path: Path, points: NDArray[np.float64], colors: NDArray[np.uint8] | None, scale_m: float = 1e-4
) -> None:
    """LAS 1.2 (format 2 with colours, 0 without), or LAZ when ``path`` ends in .laz;
    colours stored as 16-bit (× 257) as the LAS specification says."""
    header = laspy.LasHeader(point_format=2 if colors is not None else 0, version="1.2")
    header.scales = np.asarray([scale_m] * 3)
    header.offsets = np.floor(points.min(axis=0)) if len(points) else np.zeros(3)
    las = laspy.LasData(header)
    las.x, las.y, las.z = points[:, 0], points[:, 1], points[:, 2]
    if colors is not None:
        las.red, las.green, las.blue = (colors[:, k].astype(np.uint16) * 257 for k in range(3))
    las.write(str(path))


def write_ply(
    path: Path, points: NDArray[np.float64], colors: NDArray[np.uint8] | None, ascii: bool = False
) -> None:
    """A PLY cloud written by Open3D (binary little-endian, or ASCII)."""
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    if colors is not None:
        pcd.colors = o3d.utility.Vector3dVector(colors / 255.0)
    assert o3d.io.write_point_cloud(str(path), pcd, write_ascii=ascii)
