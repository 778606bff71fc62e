"""Accuracy and timing of the reconstruct stage on a generated scene with ground truth.

    python bench/reconstruct_bench.py [--scene DIR] [--work DIR] [--preset default]
        [--options '{"far_range": false}']

Generates (or reuses) a synth scenario, then runs three cases on its "before" capture —
SfM + markers (intrinsics only), known poses — and the "after" capture refined against the
"before" cloud. Writes ``bench/results/reconstruct.json``. Metrics: camera-centre error
after marker alignment (m), cloud distance to the true surface (median, p95, m),
completeness (share of the visible true surface with a cloud point within 1 cm), timings.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from workers.pipeline.geometry import pose_error
from workers.pipeline.reconstruct import options_from_preset, parse_cameras, reconstruct
from workers.pipeline.reconstruct.fusion import read_ply

ROOT = Path(__file__).resolve().parents[1]


def _scene(meshes: dict[str, o3d.geometry.TriangleMesh]) -> o3d.t.geometry.RaycastingScene:
    scene = o3d.t.geometry.RaycastingScene()
    for mesh in meshes.values():
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    return scene


@dataclass(frozen=True)
class VisibleSurface:
    """True-surface samples seen unoccluded by ≥ 2 views: (N, 3) points and unit normals (env,
    m), (N, V) which views see them, and the (V, 4, 4) env_from_cam and focal length (px)."""

    points: np.ndarray
    normals: np.ndarray
    seen: np.ndarray
    env_from_cams: np.ndarray
    focal_px: float


def visible_surface_samples(
    meshes: dict[str, o3d.geometry.TriangleMesh],
    cameras: dict[str, Any],
    n: int = 300_000,
    min_views: int = 2,
) -> VisibleSurface:
    """Points sampled on the true surface (area-uniform) seen unoccluded by ≥ min_views."""
    merged = o3d.geometry.TriangleMesh()
    for m in meshes.values():
        merged += m
    o3d.utility.random.seed(0)
    pts = np.asarray(merged.sample_points_uniformly(n).points)
    scene = _scene(meshes)
    intr = cameras["intrinsics"]
    fx, fy, cx, cy = intr["params"][:4]
    w, h = intr["width"], intr["height"]
    poses = np.stack([np.asarray(p, np.float64) for p in cameras["poses"].values()])
    seen = np.zeros((len(pts), len(poses)), bool)
    for k, env_from_cam in enumerate(poses):
        cam_from_env = np.linalg.inv(env_from_cam)
        pc = pts @ cam_from_env[:3, :3].T + cam_from_env[:3, 3]
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = fx * pc[:, 0] / z + cx, fy * pc[:, 1] / z + cy
        inside = (z > 0.05) & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
        centre = env_from_cam[:3, 3]
        d = pts - centre
        dist = np.linalg.norm(d, axis=1)
        rays = np.concatenate([np.repeat(centre[None], len(pts), 0), d / dist[:, None]], 1)
        hit = scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))["t_hit"].numpy()  # type: ignore[call-overload]
        seen[:, k] = inside & (hit >= dist - 0.002)
    keep = seen.sum(axis=1) >= min_views
    closest = scene.compute_closest_points(o3d.core.Tensor(pts[keep].astype(np.float32)))  # type: ignore[call-overload]
    normals = closest["primitive_normals"].numpy().astype(np.float64)
    return VisibleSurface(pts[keep], normals, seen[keep], poses, float(fx))


def stereo_reachable(
    surface: VisibleSurface,
    matching_error_px: float = 0.25,
    max_error_m: float = 0.01,
    max_axis_angle_deg: float = 45.0,
    min_elevation_deg: float = 15.0,
) -> np.ndarray:
    """(N,) bool: samples that some pair of views can triangulate to ``max_error_m``.

    A pair qualifies when both views see the sample at ≥ ``min_elevation_deg`` above the
    surface (block matching fails at grazing incidence) with optical axes within
    ``max_axis_angle_deg`` (the MVS stage's partner limit); a matching error of
    ``matching_error_px`` in view j moves the point along view i's ray by
    d_j · (σ / f) / sin θ (θ: the rays' angle at the sample, d_j: its distance from j).
    """
    pts, seen = surface.points, surface.seen
    centres = surface.env_from_cams[:, :3, 3]
    axes = surface.env_from_cams[:, :3, 2]
    rays = pts[:, None, :] - centres[None]  # (N, V, 3)
    dist = np.linalg.norm(rays, axis=2)
    rays /= dist[..., None]
    elevation_ok = np.abs(np.einsum("nvk,nk->nv", rays, surface.normals)) >= np.sin(
        np.radians(min_elevation_deg)
    )
    usable = seen & elevation_ok
    best = np.full(len(pts), np.inf)
    cos_axes = axes @ axes.T
    for i in range(len(centres)):
        for j in range(len(centres)):
            if i == j or cos_axes[i, j] < np.cos(np.radians(max_axis_angle_deg)):
                continue
            m = usable[:, i] & usable[:, j]
            sin = np.linalg.norm(np.cross(rays[m, i], rays[m, j]), axis=1)
            err = dist[m, j] * (matching_error_px / surface.focal_px) / np.maximum(sin, 1e-9)
            best[m] = np.minimum(best[m], err)
    return np.asarray(best <= max_error_m)


def cloud_metrics(
    cloud: np.ndarray,
    meshes: dict[str, o3d.geometry.TriangleMesh],
    surface: VisibleSurface,
    work_radius_m: float = 1.5,
) -> dict[str, Any]:
    """Distances of the cloud to the true surface; completeness over the visible surface,
    all of it, within the working area (horizontal radius ≤ work_radius_m, inside the
    camera ring, where the objects stand) and over its stereo-reachable part
    (:func:`stereo_reachable`, a second metric beside the first, not a replacement);
    completeness by the distance of the nearest camera that sees the sample."""
    visible = surface.points
    dist = _scene(meshes).compute_distance(o3d.core.Tensor(cloud.astype(np.float32))).numpy()  # type: ignore[call-overload]
    nn, _ = cKDTree(cloud).query(visible, k=1, workers=2)
    inner = np.linalg.norm(visible[:, :2], axis=1) <= work_radius_m
    in_cloud = np.linalg.norm(cloud[:, :2], axis=1) <= work_radius_m
    reach = stereo_reachable(surface)
    centres = surface.env_from_cams[:, :3, 3]
    cam_dist = np.linalg.norm(visible[:, None, :] - centres[None], axis=2)
    nearest = np.where(surface.seen, cam_dist, np.inf).min(axis=1)
    bands = {}
    for lo, hi in ((0.0, 1.5), (1.5, 2.5), (2.5, 3.5), (3.5, 4.5), (4.5, 99.0)):
        m = (nearest >= lo) & (nearest < hi)
        bands[f"{lo}-{hi}"] = {
            "share": float(m.mean()),
            "completeness_1cm": float(np.mean(nn[m] < 0.01)) if m.any() else None,
        }
    return {
        "work_radius_m": work_radius_m,
        "completeness_1cm_work_area": float(np.mean(nn[inner] < 0.01)),
        "distance_median_work_area_m": float(np.median(dist[in_cloud])),
        "distance_p95_work_area_m": float(np.percentile(dist[in_cloud], 95)),
        "points": len(cloud),
        "distance_median_m": float(np.median(dist)),
        "distance_p90_m": float(np.percentile(dist, 90)),
        "distance_p95_m": float(np.percentile(dist, 95)),
        "distance_mean_m": float(np.mean(dist)),
        "share_over_2cm": float(np.mean(dist > 0.02)),
        "completeness_1cm": float(np.mean(nn < 0.01)),
        "completeness_5mm": float(np.mean(nn < 0.005)),
        "reachable_share_of_visible": float(reach.mean()),
        "completeness_1cm_reachable": float(np.mean(nn[reach] < 0.01)),
        "completeness_1cm_by_nearest_camera_m": bands,
    }


def camera_metrics(views: Any, cameras: dict[str, Any]) -> dict[str, float]:
    errs = [pose_error(v.env_from_cam, np.asarray(cameras["poses"][v.name])) for v in views]
    t = np.array([e[0] for e in errs])
    r = np.array([e[1] for e in errs])
    return {
        "camera_centre_error_median_m": float(np.median(t)),
        "camera_centre_error_max_m": float(t.max()),
        "camera_rotation_error_median_deg": float(np.median(r)),
    }


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--scene", type=Path, default=Path("/tmp/twindelta_bench/scene"))
    parser.add_argument("--work", type=Path, default=Path("/tmp/twindelta_bench/work"))
    parser.add_argument("--preset", default="default")
    parser.add_argument(
        "--options",
        default="{}",
        help="JSON overrides of the preset, e.g. '{\"far_range\": false}' (the baseline)",
    )
    parser.add_argument("--scenario", default="moved")
    parser.add_argument("--seed", type=int, default=1, help="scene seed (when generating)")
    parser.add_argument(
        "--cases",
        default="sfm_markers,known_poses,sfm_markers_after_refined",
        help="comma-separated subset (the refined case needs sfm_markers' cloud in --work)",
    )
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "reconstruct.json")
    args = parser.parse_args()
    from workers.pipeline.synth import PRESETS, generate, load_true_surfaces

    if not (args.scene / "ground_truth.json").exists():
        t = time.perf_counter()
        generate(args.scene, args.scenario, seed=args.seed, options=PRESETS["demo"])
        print(f"generated scene in {time.perf_counter() - t:.1f} s")
    reference = json.loads((args.scene / "reference.json").read_text())
    overrides = json.loads(args.options)
    options = options_from_preset(args.preset, **overrides)
    results: dict[str, Any] = {
        "preset": args.preset,
        "overrides": overrides,
        "scene": str(args.scene),
        "scenario": args.scenario,
        "seed": args.seed,
        "cases": {},
    }
    gt = json.loads((args.scene / "ground_truth.json").read_text())

    def true_cameras(capture: str) -> dict[str, Any]:
        """cameras.json with the true poses (from ground_truth.json when not written there)."""
        raw = dict(json.loads((args.scene / capture / "cameras.json").read_text()))
        if "poses" not in raw:
            raw["poses"] = gt["camera_poses"][capture]
        return raw

    cams_raw = true_cameras("before")
    meshes = load_true_surfaces(args.scene, "before")
    visible = visible_surface_samples(meshes, cams_raw)

    def run(name: str, capture: str, with_poses: bool, reference_cloud: Path | None) -> Path:
        raw = true_cameras(capture)
        cams = parse_cameras(raw if with_poses else {"intrinsics": raw["intrinsics"]})
        work = args.work / name
        import shutil

        shutil.rmtree(work, ignore_errors=True)
        load_before = os.getloadavg()[0]
        res = reconstruct(
            args.scene / capture / "images", work, options, cams, reference, reference_cloud
        )
        cloud, _ = read_ply(res.cloud_path)
        m = load_true_surfaces(args.scene, capture)
        vis = visible if capture == "before" else visible_surface_samples(m, raw)
        case = {
            "load_average_1m": [round(load_before, 2), round(os.getloadavg()[0], 2)],
            "quality": res.quality,
            **camera_metrics(res.views, raw),
            **cloud_metrics(cloud, m, vis),
        }
        results["cases"][name] = case
        print(name, json.dumps({k: v for k, v in case.items() if k != "quality"}, indent=1))
        print(" timings", res.quality["timings_s"])
        return res.cloud_path

    cases = set(args.cases.split(","))
    before_cloud = args.work / "sfm_markers" / "cloud.ply"
    if "sfm_markers" in cases:
        before_cloud = run("sfm_markers", "before", False, None)
    if "known_poses" in cases:
        run("known_poses", "before", True, None)
    if "sfm_markers_after_refined" in cases:
        run("sfm_markers_after_refined", "after", False, before_cloud)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=1, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
