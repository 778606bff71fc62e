"""Describe a surface cloud: diameter, Open3D clouds, FPFH descriptors (whole and per view)."""

from __future__ import annotations

import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from scipy.spatial import ConvexHull, QhullError

from workers.pipeline.geometry import Points, as_points
from workers.pipeline.model.options import ModelOptions


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
            vp, vn, _ = downsample_cloud(points[vis], normals[vis], None, voxel_m)
            if len(vp) < 10:
                continue
            pts.append(vp)
            nrm.append(vn)
            feats.append(fpfh_features(make_cloud(vp, vn, None), voxel_m, nr, fr))
    return np.vstack(pts), np.vstack(nrm), np.vstack(feats)


def downsample_cloud(
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
