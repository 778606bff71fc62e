"""Pose-estimation benchmark: YCB partial views (accuracy, timings) and real data.

``python bench/pose_bench.py [--objects a,b] [--trials N] [--out bench/results/pose.json]``

YCB (Calli et al. 2015, CC BY 4.0, via elpis-lab/YCB_Dataset): for each object a scene is
made from a dense surface sample of the mesh (independent of the model sample), the part
visible from one or two viewpoints (hidden-point removal), 1 mm Gaussian noise and a
table-plane patch under it, moved by a random pose; the error of the recovered
``env_from_object`` is reported (symmetry-aware for symmetric objects). Real data: the PCL
milk carton in its Kinect scene (BSD-3) and a 3DMatch fragment pair (MIT, via
qinzheng93/GeoTransformer).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import open3d as o3d

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from workers.pipeline.geometry import Mat4, invert_rigid, pose_error, transform_points  # noqa: E402
from workers.pipeline.model import MODEL_PRESETS, ModelOptions, load_surface, prepare_model  # noqa: E402
from workers.pipeline.pose import (  # noqa: E402
    POSE_PRESETS,
    PoseResult,
    SceneCloud,
    estimate_pose,
    random_rigid,
    symmetric_pose_error,
)

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
OBJECTS = ["power_drill", "large_clamp", "extra_large_clamp", "hammer", "mustard_bottle"]


def partial_view_scene(
    mesh_path: Path,
    env_from_object: Mat4,
    rng: np.random.Generator,
    n_views: int = 1,
    noise_m: float = 0.001,
    table: bool = True,
) -> tuple[SceneCloud, np.ndarray]:
    """A synthetic scan of the object in the env frame; returns (scene, object points env)."""
    sample = ModelOptions(n_points=40000, sampling="uniform", seed=int(rng.integers(1 << 30)))
    pts, nrm, col = load_surface(mesh_path, sample)
    centre = pts.mean(axis=0)
    diam = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
    keep = np.zeros(len(pts), bool)
    for _ in range(n_views):
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        cam = centre + d * 3 * diam
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        _, idx = pcd.hidden_point_removal(cam, 100 * diam)
        keep[np.asarray(idx)] = True
    p = pts[keep] + rng.normal(scale=noise_m, size=(keep.sum(), 3))
    n = nrm[keep]
    c = None if col is None else col[keep]
    obj_env = transform_points(env_from_object, p)
    n_env = n @ env_from_object[:3, :3].T
    if table:
        # a table patch 2 mm below the object's lowest env point, 1.5 diameters wide
        lo = obj_env[:, 2].min() - 0.002
        m = 4000
        xy = obj_env[:, :2].mean(axis=0) + rng.uniform(-0.75 * diam, 0.75 * diam, size=(m, 2))
        tp = np.column_stack([xy, np.full(m, lo) + rng.normal(scale=noise_m, size=m)])
        obj_env = np.vstack([obj_env, tp])
        n_env = np.vstack([n_env, np.tile([0.0, 0.0, 1.0], (m, 1))])
        if c is not None:
            c = np.vstack([c, np.full((m, 3), 0.6)])
    return SceneCloud.create(obj_env, n_env, c), transform_points(env_from_object, p)


def run_ycb(
    names: list[str], trials: int, work: Path, seed: int = 0, options: ModelOptions = MODEL_PRESETS["default"]
) -> dict[str, object]:
    out: dict[str, object] = {}
    for name in names:
        mesh = DATA / "ycb" / name / "textured.obj"
        model = prepare_model(mesh, work / name, options)
        rows = []
        for k in range(trials):
            rng = np.random.default_rng(seed * 100 + k)
            true = random_rigid(rng, 0.5)
            scene, obj_pts = partial_view_scene(mesh, true, rng, n_views=1 + k % 2)
            t = time.perf_counter()
            res = estimate_pose(model, scene, cluster_points_env=obj_pts[rng.random(len(obj_pts)) < 0.6])
            dt = time.perf_counter() - t
            e_t, e_r = symmetric_pose_error(res.env_from_object, true, model.symmetry)
            rows.append(
                {"t_mm": e_t * 1000, "r_deg": e_r, "s": dt, "fitness": res.fitness,
                 "rmse_mm": res.inlier_rmse_m * 1000, "verified": res.verified, "source": res.source,
                 "runner_up_ratio": res.runner_up_score / res.score}
            )
            print(f"{name:18s} trial {k}: {e_t*1000:6.2f} mm {e_r:6.2f} deg {dt:5.2f} s "
                  f"fit {res.fitness:.2f} rmse {res.inlier_rmse_m*1000:.2f} mm ver {res.verified} ru {res.runner_up_score / res.score:.2f} {res.source}", flush=True)
        out[name] = {
            "symmetry": model.symmetry.kind,
            "trials": rows,
            "median_t_mm": statistics.median(r["t_mm"] for r in rows),
            "median_r_deg": statistics.median(r["r_deg"] for r in rows),
            "worst_t_mm": max(r["t_mm"] for r in rows),
            "worst_r_deg": max(r["r_deg"] for r in rows),
            "median_s": statistics.median(r["s"] for r in rows),
        }
    return out


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--objects", default=",".join(OBJECTS))
    ap.add_argument("--trials", type=int, default=6)
    ap.add_argument("--voxel-divisor", type=float, default=MODEL_PRESETS["default"].voxel_divisor)
    ap.add_argument("--work", type=Path, default=Path("/tmp/twindelta_pose_bench"))
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results" / "pose.json")
    args = ap.parse_args()
    opts = ModelOptions(voxel_divisor=args.voxel_divisor)
    res = {"ycb": run_ycb(args.objects.split(","), args.trials, args.work, options=opts)}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
