"""The last fit of a pose (workers.pipeline.pose.fit.fit_scene_to_model) and the rotation
its residuals hide, which verification reads (rotation_slack_deg).

Scans are sampled from boxes (object frame, metres) with Gaussian noise along the normal,
outliers and a patch of floor around the foot, as a reconstruction gives them.
"""

from __future__ import annotations

import numpy as np

from workers.pipeline.geometry import make_rigid, rotation_angle_deg, transform_points
from workers.pipeline.pose.fit import (
    ModelSurface,
    fit_scene_to_model,
    rotation_slack_deg,
)


def box_surface(size: tuple[float, float, float], n: int, seed: int) -> tuple[np.ndarray, ...]:
    """(n, 3) points and outward normals on a box of ``size`` with its base at z = 0."""
    rng = np.random.default_rng(seed)
    half = np.asarray(size) / 2
    areas = np.array([size[1] * size[2], size[0] * size[2], size[0] * size[1]])
    axis = rng.choice(3, n, p=areas / areas.sum())
    sign = rng.choice([-1.0, 1.0], n)
    p = rng.uniform(-half, half, (n, 3))
    p[np.arange(n), axis] = sign * half[axis]
    normals = np.zeros((n, 3))
    normals[np.arange(n), axis] = sign
    return p + np.array([0.0, 0.0, half[2]]), normals


def scan(
    points: np.ndarray,
    normals: np.ndarray,
    env_from_object: np.ndarray,
    seed: int,
    visible: np.ndarray | None = None,
) -> np.ndarray:
    """The env-frame scan of the posed surface: no underside, 1 mm noise along the normal,
    3 % outliers up to 1.5 cm, and a floor ring 2 cm wide around the foot."""
    rng = np.random.default_rng(seed)
    keep = normals[:, 2] > -0.5 if visible is None else visible
    p = points[keep] + normals[keep] * rng.normal(scale=0.001, size=(int(keep.sum()), 1))
    out = rng.random(len(p)) < 0.03
    p[out] += rng.uniform(-0.015, 0.015, (int(out.sum()), 3))
    lo, hi = points.min(axis=0), points.max(axis=0)
    floor = np.column_stack(
        [
            rng.uniform(lo[0] - 0.02, hi[0] + 0.02, 3000),
            rng.uniform(lo[1] - 0.02, hi[1] + 0.02, 3000),
            rng.normal(scale=0.001, size=3000),
        ]
    )
    return transform_points(env_from_object, np.vstack([p, floor]))


def turn(deg_xyz: tuple[float, float, float], t: tuple[float, float, float]) -> np.ndarray:
    ax, ay, az = np.radians(deg_xyz)
    rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    ry = np.array([[np.cos(ay), 0, np.sin(ay)], [0, 1, 0], [-np.sin(ay), 0, np.cos(ay)]])
    rz = np.array([[np.cos(az), -np.sin(az), 0], [np.sin(az), np.cos(az), 0], [0, 0, 1]])
    return make_rigid(rz @ ry @ rx, t)


def errors(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    return float(np.linalg.norm(a[:3, 3] - b[:3, 3])), rotation_angle_deg(a[:3, :3].T @ b[:3, :3])


def test_the_scan_is_fitted_from_any_start_within_reach() -> None:
    pts, nrm = box_surface((0.16, 0.08, 0.05), 6000, 0)
    surface = ModelSurface(pts, nrm)
    true = turn((0.0, 0.0, 30.0), (0.4, -0.2, 0.0))
    scene = scan(pts, nrm, true, 1)
    poses = []
    for start in (
        turn((2.0, -1.5, 2.5), (0.003, -0.002, 0.002)),
        turn((-2.0, 1.0, -2.0), (-0.003, 0.002, 0.0)),
    ):
        pose, weights = fit_scene_to_model(surface, scene, true @ start, 0.01, 40)
        dt, dr = errors(pose, true)
        assert dt < 0.0005 and dr < 0.2, (dt, dr)
        # the scan's points carry weight; points 1.5 cm off do not
        assert np.mean(weights[:-3000] > 0.5) > 0.8
        poses.append(pose)
    assert errors(poses[0], poses[1])[1] < 0.05


def test_the_rotation_slack_is_small_for_a_box_all_round_larger_for_a_plate_from_above() -> None:
    true = turn((0.0, 0.0, 40.0), (-0.2, 0.1, 0.0))
    pts, nrm = box_surface((0.16, 0.08, 0.05), 6000, 7)
    surface = ModelSurface(pts, nrm)
    scene = scan(pts, nrm, true, 8)
    pose, weights = fit_scene_to_model(surface, scene, true, 0.01, 30)
    box_slack = rotation_slack_deg(surface, scene, weights, pose)
    assert box_slack < 5.0
    plate, plate_n = box_surface((0.16, 0.08, 0.003), 6000, 9)
    flat = ModelSurface(plate, plate_n)
    scene = scan(plate, plate_n, true, 10, visible=plate_n[:, 2] > 0.5)
    pose, weights = fit_scene_to_model(flat, scene, true, 0.01, 30)
    # only the scan points that pair with its 3 mm rim hold its turn
    assert rotation_slack_deg(flat, scene, weights, pose) > 1.5 * box_slack


def test_the_turn_about_a_continuous_symmetry_axis_is_no_slack() -> None:
    rng = np.random.default_rng(11)
    z = rng.uniform(0.0, 0.1, 6000)
    a = rng.uniform(0.0, 2 * np.pi, 6000)
    pts = np.column_stack([0.04 * np.cos(a), 0.04 * np.sin(a), z])
    nrm = np.column_stack([np.cos(a), np.sin(a), np.zeros(6000)])
    surface = ModelSurface(pts, nrm)
    true = turn((0.0, 0.0, 10.0), (0.0, 0.0, 0.0))
    scene = scan(pts, nrm, true, 12)
    pose, weights = fit_scene_to_model(surface, scene, true, 0.01, 30)
    assert (
        rotation_slack_deg(surface, scene, weights, pose) == 180.0
        or rotation_slack_deg(surface, scene, weights, pose) > 20.0
    )
    assert rotation_slack_deg(surface, scene, weights, pose, np.array([0.0, 0.0, 1.0])) < 10.0
