"""Step 1 of pose estimation: the scene region around a changed cluster.

A sphere of ``crop_factor × diameter`` around the cluster (grown to cover the cluster) is
cropped from the scene (environment frame, metres), thinned to ``v/4`` when dense, given
normals when it has none (oriented away from the cluster centre, near-horizontal ones
facing up), and the plane the object stands on is found and removed. The result is
downsampled at the model's feature voxel ``v`` and described by FPFH for RANSAC.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from workers.pipeline.errors import InputError, RegistrationError, ShapeError
from workers.pipeline.geometry import Mat4, Points, as_mat4, as_points
from workers.pipeline.model import PreparedModel, fpfh_features, make_cloud
from workers.pipeline.pose.fit import Target, median_spacing_m, normalised
from workers.pipeline.pose.options import PoseOptions

#: points sampled for the scan's spacing about the object (its median is stable at this size)
SPACING_SAMPLE = 5000


@dataclass(frozen=True)
class SceneCloud:
    """Scene points in the environment frame: (N, 3) metres, optional unit normals and
    colours in [0, 1], both (N, 3). Non-finite points are dropped on construction via
    :meth:`create`."""

    points: Points
    normals: Points | None = None
    colors: Points | None = None

    @classmethod
    def create(
        cls, points: ArrayLike, normals: ArrayLike | None = None, colors: ArrayLike | None = None
    ) -> SceneCloud:
        """Check shapes (ShapeError) and drop non-finite rows."""
        p = as_points(points, "scene points")
        n = None if normals is None else as_points(normals, "scene normals")
        c = None if colors is None else as_points(colors, "scene colors")
        for name, a in (("normals", n), ("colors", c)):
            if a is not None and a.shape != p.shape:
                raise ShapeError(f"scene {name} must match points {p.shape}, got {a.shape}")
        keep = np.isfinite(p).all(axis=1)
        if n is not None:
            keep &= np.isfinite(n).all(axis=1)
        return cls(p[keep], None if n is None else n[keep], None if c is None else c[keep])

    @classmethod
    def from_file(cls, path: Path, viewpoint_env: ArrayLike | None = None) -> SceneCloud:
        """Read a cloud file. Without normals in the file: with ``viewpoint_env`` (the camera
        of a single depth frame, metres) they are estimated and oriented towards it; without
        it they are left to the crop, which orients them as the service does (away from the
        cluster centre, horizontal ones up)."""
        pcd = o3d.io.read_point_cloud(Path(path)).remove_non_finite_points()
        if len(pcd.points) == 0:
            raise InputError(f"{Path(path).name}: no finite points could be read")
        if not pcd.has_normals() and viewpoint_env is not None:
            pts = np.asarray(pcd.points)
            ext = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
            pcd.estimate_normals(
                o3d.geometry.KDTreeSearchParamHybrid(radius=ext / np.sqrt(len(pts)) * 6, max_nn=30)
            )
            pcd.orient_normals_towards_camera_location(np.asarray(viewpoint_env, np.float64))
        return cls.create(
            np.asarray(pcd.points),
            np.asarray(pcd.normals) if pcd.has_normals() else None,
            np.asarray(pcd.colors) if pcd.has_colors() else None,
        )


@dataclass(frozen=True)
class PoseInputs:
    """The checked inputs of one pose estimate (environment frame, metres): ``cluster``
    (K, 3) points or None, ``centre`` (3,), ``previous`` 4×4 env_from_object or None,
    ``up`` (3,) unit."""

    cluster: Points | None
    centre: NDArray[np.float64]
    previous: Mat4 | None
    up: NDArray[np.float64]


@dataclass(frozen=True)
class SceneRegion:
    """The scene region of one pose estimate. ``n_points``: points within ``radius_m`` of the
    cluster centre; ``fine``: the region (support plane removed, unit normals) as an Open3D
    cloud and its ICP ``target_fine``; ``down``: ``fine`` downsampled at the model voxel with
    its ``fpfh`` (M, 33) and ``target_down``; ``support``: the plane (4,) ``[n, d]`` the
    object stands on or None, ``band_m`` its band, ``on_support`` (S, 3) scene points on
    it; ``support_removed``: how many points its removal took out; ``spacing_m``: the
    median nearest-neighbour distance of the points within ``radius_m`` (the scan's density
    about the object, metres)."""

    n_points: int
    radius_m: float
    fine: o3d.geometry.PointCloud
    down: o3d.geometry.PointCloud
    fpfh: NDArray[np.float64]
    target_fine: Target
    target_down: Target
    support: NDArray[np.float64] | None
    band_m: float
    on_support: Points
    support_removed: int
    spacing_m: float


@dataclass(frozen=True)
class _Support:
    plane: NDArray[np.float64] | None
    on_support: Points
    cloud: o3d.geometry.PointCloud


def _crop(scene: SceneCloud, centre: NDArray[np.float64], radius: float) -> SceneCloud:
    """The scene points within ``radius`` metres of ``centre`` (3,), with their normals and
    colours."""
    # a slab in x first: the full test on every point of a 1.9M-point scene costs 3-4× more
    keep = np.flatnonzero(np.abs(scene.points[:, 0] - centre[0]) <= radius * (1.0 + 1e-9))
    near = scene.points[keep] - centre
    keep = keep[np.einsum("ij,ij->i", near, near) <= radius * radius]
    return SceneCloud(
        scene.points[keep],
        None if scene.normals is None else scene.normals[keep],
        None if scene.colors is None else scene.colors[keep],
    )


def _orient_scene_normals(
    normals: Points, points: Points, centre: NDArray[np.float64], up: NDArray[np.float64]
) -> Points:
    """Orient estimated (N, 3) normals without a viewpoint: away from the cluster centre,
    except near-horizontal surfaces (normal within 37° of ``up``), which face up — the table
    under an object is seen from above, and an object's hidden underside is not scanned."""
    out = normals.copy()
    out[np.einsum("ij,ij->i", out, points - centre) < 0] *= -1.0
    along = out @ up
    out[(np.abs(along) > 0.8) & (along < 0)] *= -1.0
    return out


def _refit_plane(
    points: Points,
    inliers: NDArray[np.bool_],
    up: NDArray[np.float64],
    rounds: int = 3,
) -> NDArray[np.float64]:
    """The plane (4,) ``[n, d]`` (n toward ``up``) of the (N, 3) points' ``inliers``, refitted
    on the inliers within 3 robust σ of each fit: a narrow band around a RANSAC plane keeps
    that plane's tilt (three noisy points' tilt, about a degree on a 2 mm noisy floor)."""
    plane = np.zeros(4)
    for i in range(rounds + 1):
        pick = points[inliers]
        centre = pick.mean(axis=0)
        normal = np.linalg.svd(pick - centre, full_matrices=False)[2][2]
        normal = normal if normal @ up > 0 else -normal
        plane = np.append(normal, -normal @ centre)
        if i == rounds:
            break
        resid = points @ plane[:3] + plane[3]
        sigma = 1.4826 * float(np.median(np.abs(resid[inliers])))
        wider = np.abs(resid) < max(3.0 * sigma, 1e-4)
        if wider.sum() < 3:
            break
        inliers = wider
    return plane


def support_plane(
    points: Points,
    normals: Points,
    up: NDArray[np.float64],
    cluster: Points,
    band: float,
    seed: int,
) -> NDArray[np.float64] | None:
    """The plane (4,) ``[n, d]`` (unit ``n`` within 10° of ``up``, height ``n·p + d``) that the
    object stands on: the largest plane (RANSAC, 200 draws, seeded) of the near-horizontal
    (N, 3) scene points that at least 10 % of them fit within ``band / 2`` and that the
    (K, 3) cluster's median lies more than ``band`` above (a box's own top face is not its
    support); None if none."""
    rng = np.random.default_rng(seed)
    horizontal = points[np.abs(normals @ up) > np.cos(np.radians(25.0))]
    for _ in range(2):
        if len(horizontal) < 100:
            return None
        tri = horizontal[rng.integers(0, len(horizontal), size=(200, 3))]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        n *= np.where(n @ up < 0, -1.0, 1.0)[:, None]
        ok = n @ up > np.cos(np.radians(10.0))
        if not ok.any():
            return None
        n, d = n[ok], -np.einsum("ij,ij->i", n[ok], tri[ok, 0])
        sample = horizontal[rng.choice(len(horizontal), min(len(horizontal), 2000), replace=False)]
        counts = (np.abs(sample @ n.T + d) < band / 2).sum(axis=0)
        best = int(np.argmax(counts))
        inliers = np.abs(horizontal @ n[best] + d[best]) < band / 2
        if inliers.sum() < 0.1 * len(horizontal):
            return None
        # the plane's own points away from the object: its foot smears the floor upward
        away = np.isinf(cKDTree(cluster).query(horizontal, distance_upper_bound=2 * band)[0])
        if (inliers & away).sum() < 30:
            away[:] = True
        out = _refit_plane(horizontal[away], inliers[away], up)
        if out[:3] @ up < np.cos(np.radians(10.0)):
            return None
        if float(np.median(cluster @ out[:3] + out[3])) > band:
            return out
        # a horizontal face of the object itself: look below it
        horizontal = horizontal[horizontal @ out[:3] + out[3] < -band]
    return None


def check_inputs(
    cluster_points_env: ArrayLike | None,
    centre_env: ArrayLike | None,
    previous_env_from_object: ArrayLike | None,
    up_env: ArrayLike,
) -> PoseInputs:
    """Checked :class:`PoseInputs`; an empty cluster counts as none. InputError when neither a
    cluster nor a centre is given, ShapeError for wrong shapes or a zero ``up_env``."""
    cluster = (
        None if cluster_points_env is None else as_points(cluster_points_env, "cluster points")
    )
    if cluster is not None and len(cluster) == 0:
        cluster = None
    if cluster is not None:
        centre = cluster.mean(axis=0)
    elif centre_env is not None:
        centre = np.asarray(centre_env, dtype=np.float64).reshape(-1)
        if centre.shape != (3,) or not np.isfinite(centre).all():
            raise ShapeError(f"centre_env must be a finite (3,), got {centre.shape}")
    else:
        raise InputError("estimate_pose needs cluster_points_env or centre_env")
    previous = (
        None if previous_env_from_object is None else as_mat4(previous_env_from_object, "previous")
    )
    up = np.asarray(up_env, dtype=np.float64).reshape(-1)
    if up.shape != (3,) or np.linalg.norm(up) == 0:
        raise ShapeError("up_env must be a non-zero (3,) vector")
    return PoseInputs(cluster, centre, previous, up / np.linalg.norm(up))


def crop_radius(model: PreparedModel, inputs: PoseInputs, options: PoseOptions) -> float:
    """``crop_factor × diameter``, grown to cover the cluster plus a quarter diameter (at most
    one diameter, or the crop factor's radius when that is larger); metres."""
    diam = model.diameter_m
    radius = options.crop_factor * diam
    if inputs.cluster is not None:
        extent = float(np.sqrt(np.max(np.sum((inputs.cluster - inputs.centre) ** 2, axis=1))))
        radius = min(max(radius, extent + 0.25 * diam), max(diam, options.crop_factor * diam))
    return radius


def _region_cloud(
    model: PreparedModel, crop: SceneCloud, inputs: PoseInputs
) -> o3d.geometry.PointCloud:
    """The cropped points as an Open3D cloud, thinned to ``v/4`` when far denser than the
    model, with normals estimated and oriented (:func:`_orient_scene_normals`) when absent."""
    v = model.voxel_m
    cloud = make_cloud(crop.points, crop.normals, crop.colors)
    if len(crop.points) > 4 * len(model.points):
        # a dense reconstruction: v/4 keeps every detail the fit uses, at a fraction of the
        # cost of normals and neighbour queries on every point
        cloud = cloud.voxel_down_sample(v / 4)
    if crop.normals is None:
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * v, max_nn=30))
        cloud.normals = o3d.utility.Vector3dVector(
            _orient_scene_normals(
                np.asarray(cloud.normals), np.asarray(cloud.points), inputs.centre, inputs.up
            )
        )
    return cloud


def _remove_support(
    cloud: o3d.geometry.PointCloud, inputs: PoseInputs, band: float, options: PoseOptions
) -> _Support:
    """Find the support plane (when ``support_band_voxels`` > 0) and remove the points up to
    ``band`` above it when at least 30 remain: the floor or table the object stands on is
    not the object, and a flat object laid into it upside down fits it better."""
    points = np.asarray(cloud.points)
    cluster_low = inputs.cluster if inputs.cluster is not None else inputs.centre[None, :]
    plane = (
        support_plane(points, np.asarray(cloud.normals), inputs.up, cluster_low, band, options.seed)
        if options.support_band_voxels > 0
        else None
    )
    on_support = np.zeros((0, 3))
    if plane is not None:
        height = points @ plane[:3] + plane[3]
        on_support = points[np.abs(height) < band / 2]
        above = np.flatnonzero(height > band)
        if len(above) >= 30:
            cloud = cloud.select_by_index(above.tolist())
    return _Support(plane, on_support, cloud)


def crop_scene(
    model: PreparedModel, scene: SceneCloud, inputs: PoseInputs, options: PoseOptions
) -> SceneRegion:
    """Step 1: the :class:`SceneRegion` around the cluster. RegistrationError when fewer than
    30 scene points lie within the crop radius."""
    v = model.voxel_m
    radius = crop_radius(model, inputs, options)
    crop = _crop(scene, inputs.centre, radius)
    if len(crop.points) < 30:
        raise RegistrationError(
            f"only {len(crop.points)} scene points within {radius:.3f} m of the cluster centre"
        )
    full = _region_cloud(model, crop, inputs)
    n_full = len(full.points)
    band = min(options.support_band_voxels * v, options.max_inlier_distance_m)
    support = _remove_support(full, inputs, band, options)
    fine = support.cloud
    down = fine.voxel_down_sample(v)
    down.normals = o3d.utility.Vector3dVector(normalised(np.asarray(down.normals)))
    if fine.has_normals():
        fine.normals = o3d.utility.Vector3dVector(normalised(np.asarray(fine.normals)))
    n_opts = model.summary.get("options", {})
    fpfh = fpfh_features(
        down,
        v,
        float(n_opts.get("normal_radius_voxels", 2.0)),
        float(n_opts.get("feature_radius_voxels", 5.0)),
    )
    return SceneRegion(
        n_points=len(crop.points),
        radius_m=radius,
        fine=fine,
        down=down,
        fpfh=fpfh,
        target_fine=Target(fine),
        target_down=Target(down),
        support=support.plane,
        band_m=band,
        on_support=support.on_support,
        support_removed=n_full - len(fine.points),
        spacing_m=median_spacing_m(crop.points, SPACING_SAMPLE, options.seed),
    )
