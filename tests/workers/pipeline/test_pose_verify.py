"""Verification of a pose (workers.pipeline.pose.verify): the 3D rejections and the
re-projection check against the detector's boxes.

The re-projection oracle: a box model 1 m in front of two cameras, the detector's boxes
being the true pose's own projection. The right pose re-projects onto them (IoU ≥ 0.9; the
1st-99th percentile box of the projected points against their full extent loses a few
per cent), a pose 20 cm to the side misses them (IoU 0).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from workers.pipeline.compare.data import Camera, CaptureData
from workers.pipeline.compare.visibility import DepthMap, render_depth
from workers.pipeline.geometry import make_rigid, rotation_about_unit_axis, transform_points
from workers.pipeline.model.symmetry_group import SymmetrySpec
from workers.pipeline.pose import POSE_PRESETS, RUNNER_UP_REASON, PoseResult, Trial, posing
from workers.pipeline.pose.crop import SceneCloud
from workers.pipeline.pose.photo_edges import CaptureSight
from workers.pipeline.pose.refine import Refinement
from workers.pipeline.pose.result import Alternative
from workers.pipeline.pose.verify import (
    ReprojectionOptions,
    cluster_coverage,
    inside_hull,
    reprojection_check,
    verify_fit,
    visible_fitness,
)

K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
CLASS_ID = 2


def box_model(n: int = 4000, seed: int = 0) -> np.ndarray:
    """(n, 3) points on the surface of a 0.2 × 0.1 × 0.1 m box centred at the origin."""
    rng = np.random.default_rng(seed)
    p = rng.uniform(-0.5, 0.5, size=(n, 3))
    axis = rng.integers(0, 3, n)
    p[np.arange(n), axis] = np.sign(p[np.arange(n), axis]) * 0.5
    return p * np.array([0.2, 0.1, 0.1])


def cameras() -> list[Camera]:
    """Two cameras at z = 0 looking along +z (OpenCV axes), 10 cm apart."""
    return [
        Camera(f"cam{i}", K, 640, 480, make_rigid(np.eye(3), (-0.05 + 0.1 * i, 0.0, 0.0)))
        for i in range(2)
    ]


def yolo_row(camera: Camera, points_env: np.ndarray, class_id: int) -> np.ndarray:
    """The detector's row (class, cx, cy, w, h; normalised) of the points' full 2D extent."""
    p_cam = transform_points(camera.cam_from_env, points_env)
    uv = p_cam[:, :2] / p_cam[:, 2:] @ K[:2, :2].T + K[:2, 2]
    (x1, y1), (x2, y2) = uv.min(axis=0), uv.max(axis=0)
    w, h = camera.width, camera.height
    return np.array(
        [[class_id, (x1 + x2) / 2 / w, (y1 + y2) / 2 / h, (x2 - x1) / w, (y2 - y1) / h]]
    )


@dataclass(frozen=True)
class BoxScene:
    """The box model (object frame), its true ``env_from_object``, the cameras and the
    detector's rows per camera name."""

    model: np.ndarray
    env_from_object: np.ndarray
    cameras: list[Camera]
    detections: dict[str, np.ndarray]


@pytest.fixture
def scene() -> BoxScene:
    model = box_model()
    env_from_object = make_rigid(np.eye(3), (0.0, 0.0, 1.0))
    cams = cameras()
    posed = transform_points(env_from_object, model)
    return BoxScene(
        model, env_from_object, cams, {c.name: yolo_row(c, posed, CLASS_ID) for c in cams}
    )


def test_the_right_pose_reprojects_onto_the_detections(scene: BoxScene) -> None:
    model, env_from_object = scene.model, scene.env_from_object
    cams, detections = scene.cameras, scene.detections
    check = reprojection_check(model, env_from_object, CLASS_ID, cams, detections)
    assert check.passed and check.views == 2 and check.visible_views == 2
    assert check.mean_iou >= 0.9
    assert check.to_json()["passed"] is True


def test_a_shifted_pose_misses_them(scene: BoxScene) -> None:
    model, env_from_object = scene.model, scene.env_from_object
    cams, detections = scene.cameras, scene.detections
    shifted = make_rigid(np.eye(3), (0.2, 0.0, 0.0)) @ env_from_object
    check = reprojection_check(model, shifted, CLASS_ID, cams, detections)
    assert not check.passed and check.views == 2 and check.mean_iou < 0.1


def test_another_class_or_too_few_views_do_not_pass(scene: BoxScene) -> None:
    model, env_from_object = scene.model, scene.env_from_object
    cams, detections = scene.cameras, scene.detections
    other = reprojection_check(model, env_from_object, CLASS_ID + 1, cams, detections)
    assert not other.passed and other.views == 0 and other.visible_views == 2
    assert other.mean_iou == 0.0
    one = reprojection_check(model, env_from_object, CLASS_ID, cams[:1], detections)
    assert not one.passed and one.views == 1 and one.mean_iou >= 0.9
    lenient = ReprojectionOptions(min_views=1)
    assert reprojection_check(
        model, env_from_object, CLASS_ID, cams[:1], detections, None, lenient
    ).passed
    behind = make_rigid(np.eye(3), (0.0, 0.0, -1.0))
    unseen = reprojection_check(model, behind, CLASS_ID, cams, detections)
    assert unseen.visible_views == 0 and not unseen.passed


def test_depth_maps_must_match_the_cameras(scene: BoxScene) -> None:
    model, env_from_object = scene.model, scene.env_from_object
    cams, detections = scene.cameras, scene.detections
    with pytest.raises(ValueError, match="one map per camera"):
        reprojection_check(model, env_from_object, CLASS_ID, cams, detections, depth_maps=[])


def refinement(
    fitness: float,
    rmse_m: float,
    score: float = 1.0,
    runner_up: float = 0.0,
    slack_deg: float = 5.0,
    turn_deg: float = 1.0,
) -> Refinement:
    pose = np.eye(4)
    return Refinement(
        pose,
        score,
        runner_up,
        fitness,
        rmse_m,
        0.005,
        Trial("t", score, fitness, rmse_m, 0.0, pose),
        rotation_slack_deg=slack_deg,
        final_turn_deg=turn_deg,
    )


def test_cluster_coverage_counts_what_lies_inside_the_object() -> None:
    """Stereo closes a hollow object's opening with points in its cavity: inside the posed
    model's convex hull they are explained; the same points beside it are not. An open
    box 0.2 × 0.1 × 0.1 m posed 1 m away and turned, voxel 5 mm."""
    o, v = POSE_PRESETS["default"], 0.005
    walls = box_model(4000)
    walls = walls[walls[:, 2] < 0.05]  # no top: a hollow tray
    pose = make_rigid(rotation_about_unit_axis([0.0, 0.0, 1.0], np.radians(30.0)), (1.0, 0.5, 0.0))
    rng = np.random.default_rng(1)
    cavity = rng.uniform([-0.08, -0.03, -0.03], [0.08, 0.03, 0.04], size=(1000, 3))
    seen = transform_points(pose, walls[:3000])
    inside = transform_points(pose, cavity)
    beside = transform_points(pose, cavity + np.array([0.3, 0.0, 0.0]))
    assert cluster_coverage(np.vstack([seen, inside]), walls, pose, v, o) == 1.0
    assert cluster_coverage(np.vstack([seen, beside]), walls, pose, v, o) == 0.75
    assert inside_hull(walls, cavity).all()
    assert not inside_hull(walls * np.array([1.0, 1.0, 0.0]), cavity).any()  # no volume


def test_verify_fit_names_each_failed_figure() -> None:
    """Each threshold rejects on its own, with a message naming the figure; a good fit with
    a covered cluster is verified, whatever its inlier RMSE (the cloud's noise). Voxel 10 mm."""
    o, v = POSE_PRESETS["default"], 0.01
    model = box_model(2000)
    good = verify_fit(refinement(0.5, 0.001), model, model + 0.0005, v, o)
    assert good.verified and good.rejections == () and good.cluster_coverage == 1.0
    assert verify_fit(refinement(0.5, 0.001), model, None, v, o).cluster_coverage is None
    cases = {
        "fitness 0.10 < 0.25": refinement(0.1, 0.001),
        f"{RUNNER_UP_REASON} 0.90 of the best": refinement(0.5, 0.001, 1.0, 0.9),
        "the scan's residuals hide a turn of 25.0° (> 20.0°)": refinement(
            0.5, 0.001, slack_deg=25.0
        ),
        "the last fit turned the ICP pose by 3.5° (> 3.0°)": refinement(0.5, 0.001, turn_deg=3.5),
    }
    for reason, fit in cases.items():
        result = verify_fit(fit, model, None, v, o)
        assert not result.verified and len(result.rejections) == 1, result
        assert result.rejections[0].startswith(reason), result
    elsewhere = model + np.array([0.0, 0.0, 0.5])  # a cluster the posed model does not explain
    uncovered = verify_fit(refinement(0.5, 0.001), model, elsewhere, v, o)
    assert uncovered.rejections == ("cluster coverage 0.00 < 0.85",)
    noisy = verify_fit(refinement(0.5, 0.004), model, None, v, o)  # RMSE 0.4 voxel
    assert noisy.verified, noisy
    nothing = verify_fit(refinement(0.0, 0.0), model, None, v, o)  # no inlier at all
    assert nothing.rejections == ("fitness 0.00 < 0.25",)
    lenient = replace(o, min_fitness=0.0)
    assert verify_fit(refinement(0.0, 0.0), model, None, v, lenient).rejections == (
        "fitness 0.00 < 0.00",
    )


def box_normals(points: np.ndarray) -> np.ndarray:
    """(n, 3) unit outward normals of :func:`box_model` points (the face each lies on)."""
    half = np.array([0.1, 0.05, 0.05])
    rows = np.arange(len(points))
    axis = np.argmax(np.abs(points) / half, axis=1)
    normals = np.zeros_like(points)
    normals[rows, axis] = np.sign(points[rows, axis])
    return normals


QUARTER_ABOUT_Y = make_rigid(
    np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]), (0.0, 0.0, 0.0)
)


def seen_face(scene: BoxScene) -> tuple[np.ndarray, np.ndarray, list[DepthMap]]:
    """The box's normals, the scan (the face the two cameras see at its true pose, z =
    0.95 m) and the cameras' z-buffers of that scan."""
    normals = box_normals(scene.model)
    scan = transform_points(scene.env_from_object, scene.model[normals[:, 2] < -0.5])
    maps = [render_depth(c, scan.astype(np.float32)) for c in scene.cameras]
    return normals, scan, maps


def test_visible_fitness_is_the_share_of_the_seen_surface_the_scan_holds(scene: BoxScene) -> None:
    """The right pose's seen surface lies on the scan; the box turned a quarter about y
    stands 5 cm proud of it (its face towards the cameras at z = 0.9 m has no scan point
    near); the box 30 cm further back hides behind the scan (too few points seen); no
    cameras, no figure."""
    normals, scan, maps = seen_face(scene)

    def figure(env_from_object: np.ndarray, depth_maps: list[DepthMap]) -> float | None:
        return visible_fitness(scene.model, normals, env_from_object, scan, depth_maps, 0.0025)

    assert figure(scene.env_from_object, maps) == 1.0
    assert figure(scene.env_from_object @ QUARTER_ABOUT_Y, maps) == 0.0
    assert figure(make_rigid(np.eye(3), (0.0, 0.0, 1.3)), maps) is None
    assert figure(scene.env_from_object, []) is None


def near_tie(chosen: np.ndarray, rival: np.ndarray, n_points: int) -> PoseResult:
    """The pose step's result: ``chosen``, with the distinct ``rival`` scoring 0.95 of it."""
    return PoseResult(
        env_from_object=chosen,
        fitness=0.5,
        inlier_rmse_m=0.001,
        inlier_distance_m=0.0025,
        score=1.0,
        runner_up_score=0.95,
        cluster_coverage=1.0,
        verified=False,
        rejections=(f"{RUNNER_UP_REASON} 0.95 of the best (> 0.85)",),
        ambiguous=False,
        equivalent_poses=(),
        symmetry_axis_env=None,
        symmetry_origin_env=None,
        chosen_by="unique",
        source="test",
        trials=(),
        n_scene_points=n_points,
        alternatives=(Alternative(0.95, rival),),
    )


def test_what_the_cameras_saw_settles_a_near_tie_for_the_pose_steps_choice(
    scene: BoxScene, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A near-tie of the true pose and the box turned a quarter about y, both standing the
    same way up. When the pose step chose the true pose, its seen surface lies on the scan
    (visible fitness 1) and the turned one's does not (0): the tie is settled by
    visibility and the pose verified. When it chose the turned pose, visibility does not
    pick another; the detector's boxes do (the true pose re-projects onto them). Without
    the capture's depth maps there is no visible fitness and the boxes decide."""
    normals, scan, maps = seen_face(scene)
    after = CaptureData(scan, tuple(scene.cameras), scene.detections)
    model: Any = SimpleNamespace(
        points=scene.model,
        normals=normals,
        centre_object=np.zeros(3),
        up_object=np.array([-1.0, 0.0, 1.0]) / np.sqrt(2.0),  # upright in both poses
        symmetry=SymmetrySpec(),
        diameter_m=0.245,
    )
    change: Any = SimpleNamespace(
        type="added", cluster=SimpleNamespace(points_env=scan), previous_env_from_object=None
    )
    true, turned = scene.env_from_object, scene.env_from_object @ QUARTER_ABOUT_Y
    options = POSE_PRESETS["default"]

    def posed(chosen: np.ndarray, rival: np.ndarray, depth_maps: Any) -> dict[str, Any]:
        monkeypatch.setattr(posing, "estimate_pose", lambda *a, **k: near_tie(chosen, rival, 9))
        cloud = SceneCloud.create(scan)
        sight = CaptureSight(after, depth_maps)
        return posing.pose_change(change, model, cloud, sight, CLASS_ID, options)

    kept = posed(true, turned, maps)
    quality = kept["pose_quality"]
    np.testing.assert_allclose(kept["pose"], true)
    assert quality["settled_by_visibility"] == {"visible_fitness": 1.0, "best_rival": 0.0}
    assert quality["chosen_by"] == "unique" and quality["visible_fitness"] == 1.0
    assert quality["verified"] is True and quality["reasons"] == [], quality
    for depth_maps in (maps, None):
        switched = posed(turned, true, depth_maps)
        quality = switched["pose_quality"]
        np.testing.assert_allclose(switched["pose"], true)
        assert "settled_by_visibility" not in quality and quality["chosen_by"] == "reprojection"
        assert quality["settled_by_reprojection"]["mean_iou"] > 0.9, quality
        assert quality["visible_fitness"] == (1.0 if depth_maps else None)
