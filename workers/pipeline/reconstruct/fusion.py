"""Fusion of consistent depth points into one cloud, outlier removal, PLY I/O, and the
pycolmap CUDA dense path (used automatically where ``pycolmap.has_cuda``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from workers.pipeline.geometry import as_points
from workers.pipeline.reconstruct.errors import DenseReconstructionFailed
from workers.pipeline.reconstruct.options import ReconstructOptions

FloatArray = NDArray[np.float64]


def to_o3d(
    points: FloatArray, colors_rgb: NDArray[np.uint8] | None = None
) -> o3d.geometry.PointCloud:
    """Open3D cloud from (N, 3) metres and optional (N, 3) uint8 RGB."""
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(as_points(points)))
    if colors_rgb is not None:
        pcd.colors = o3d.utility.Vector3dVector(np.asarray(colors_rgb, np.float64) / 255.0)
    return pcd


def from_o3d(pcd: o3d.geometry.PointCloud) -> tuple[FloatArray, NDArray[np.uint8]]:
    """((N, 3) float64 metres, (N, 3) uint8 RGB; zeros when the cloud has no colours)."""
    pts = np.asarray(pcd.points, dtype=np.float64)
    if pcd.has_colors():
        cols = np.clip(np.rint(np.asarray(pcd.colors) * 255.0), 0, 255).astype(np.uint8)
    else:
        cols = np.zeros((len(pts), 3), np.uint8)
    return pts, cols


def fuse_points(
    points: FloatArray, colors_rgb: NDArray[np.uint8], options: ReconstructOptions
) -> tuple[FloatArray, NDArray[np.uint8]]:
    """Voxel-average at ``voxel_size_m`` then statistical outlier removal.

    (N, 3) metres and (N, 3) uint8 in, (M, 3) and (M, 3) out. Raises
    DenseReconstructionFailed when nothing is left.
    """
    pcd = to_o3d(points, colors_rgb)
    if options.voxel_size_m > 0:
        pcd = pcd.voxel_down_sample(options.voxel_size_m)
    if options.sor_neighbours > 0 and len(pcd.points) > options.sor_neighbours:
        pcd, _ = pcd.remove_statistical_outlier(options.sor_neighbours, options.sor_std_ratio)
    pts, cols = from_o3d(pcd)
    if len(pts) == 0:
        raise DenseReconstructionFailed("the fused cloud is empty after outlier removal")
    return pts, cols


def write_ply(path: Path, points: FloatArray, colors_rgb: NDArray[np.uint8]) -> None:
    """Write a binary, coloured PLY (points in metres)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    pcd = to_o3d(points, colors_rgb)
    if not o3d.io.write_point_cloud(str(path), pcd, write_ascii=False):  # type: ignore[arg-type]
        raise OSError(f"cannot write {path}")


def read_ply(path: Path) -> tuple[FloatArray, NDArray[np.uint8]]:
    """Read a point cloud file: ((N, 3) metres, (N, 3) uint8 RGB)."""
    return from_o3d(o3d.io.read_point_cloud(str(path)))  # type: ignore[arg-type]


def colmap_dense(  # pragma: no cover - needs a CUDA build of pycolmap
    sparse_dir: Path, images_dir: Path, work_dir: Path
) -> tuple[FloatArray, NDArray[np.uint8]]:
    """pycolmap PatchMatch stereo + stereo fusion on a sparse model already in the env frame.

    Writes ``<work_dir>/dense`` (undistorted images, depth maps, fused.ply).
    """
    import pycolmap

    dense = Path(work_dir) / "dense"
    dense.mkdir(parents=True, exist_ok=True)
    pycolmap.undistort_images(dense, sparse_dir, images_dir)
    pycolmap.patch_match_stereo(dense)
    fused = dense / "fused.ply"
    pycolmap.stereo_fusion(fused, dense, output_type="PLY")
    return read_ply(fused)
