"""Pose estimation: oracles with known poses, symmetry handling, verification, real data.

Tolerances. Synthetic scenes are partial views (hidden-point removal) of an independent
dense surface sample of the YCB mesh with 1 mm Gaussian noise; the registration uses a
6000-point model sample (about 2.5 mm spacing). Measured errors are about 1 mm and
0.2-0.7°, so the tests assert 5 mm and 2° (the issue's per-object target): tight enough to
catch a wrong or unrefined pose (a RANSAC-only pose is off by about one voxel, 9 mm).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial import ConvexHull, cKDTree

from tests.workers.pipeline.compare_scene import look_at
from workers.pipeline.__main__ import main as pipeline_main
from workers.pipeline.compare import Camera
from workers.pipeline.compare.visibility import depth_votes, render_depth
from workers.pipeline.errors import InputError, RegistrationError, ShapeError
from workers.pipeline.geometry import (
    axis_angle_matrix,
    invert_rigid,
    make_rigid,
    pose_error,
    transform_points,
)
from workers.pipeline.model import ModelOptions, PreparedModel, load_surface, prepare_model
from workers.pipeline.model.symmetry_group import symmetric_pose_error
from workers.pipeline.pose import (
    POSE_PRESETS,
    PoseOptions,
    SceneCloud,
    estimate_pose,
    random_rigid,
)
from workers.pipeline.pose import estimate as pose_estimate_module
from workers.pipeline.pose.candidates import (
    PREVIOUS_TURNS,
    previous_on_cluster,
    upright_on_cluster,
)
from workers.pipeline.pose.crop import check_inputs, support_plane
from workers.pipeline.pose.fit import (
    ModelSurface,
    exclusion_factor,
    fit_scene_to_model,
    hull_normals,
    out_of_support,
    resting_turn,
)
from workers.pipeline.pose.refine import Refiner
from workers.pipeline.pose.verify import cluster_coverage
from workers.pipeline.seeded import seeded_open3d

UP = np.array([0.0, 0.0, 1.0])


@pytest.fixture(scope="module")
def ycb_models(
    shared_data: Path, tmp_path_factory: pytest.TempPathFactory
) -> dict[str, PreparedModel]:
    work = tmp_path_factory.mktemp("models")
    names = ("power_drill", "master_chef_can", "wood_block", "bowl", "mustard_bottle")
    return {n: prepare_model(shared_data / "ycb" / n / "textured.obj", work / n) for n in names}


def partial_view(
    mesh: Path,
    env_from_object: np.ndarray,
    seed: int,
    n_views: int = 1,
    table: bool = True,
    camera_dirs: list[np.ndarray] | None = None,
) -> tuple[SceneCloud, np.ndarray]:
    """A synthetic scan: visible part of a dense sample, 1 mm noise, a table beneath it at
    its lowest point (where it rests).

    Returns the scene (env frame) and the object's scanned points (env frame)."""
    rng = np.random.default_rng(seed)
    pts, nrm, col = load_surface(
        mesh, ModelOptions(n_points=30000, sampling="uniform", seed=seed + 7)
    )
    centre = pts.mean(axis=0)
    diam = float(np.linalg.norm(np.ptp(pts, axis=0)))
    keep = np.zeros(len(pts), bool)
    dirs = camera_dirs or [rng.normal(size=3) for _ in range(n_views)]
    for d in dirs:
        d = np.asarray(d, float) / np.linalg.norm(d)
        # camera direction given in the env frame: bring it into the object frame
        d_obj = env_from_object[:3, :3].T @ d
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        _, idx = cloud.hidden_point_removal(centre + 3 * diam * d_obj, 100 * diam)
        keep[np.asarray(idx)] = True
    obj = transform_points(
        env_from_object, pts[keep] + rng.normal(scale=0.001, size=(keep.sum(), 3))
    )
    normals = nrm[keep] @ env_from_object[:3, :3].T
    colors = None if col is None else col[keep]
    scene_pts, scene_nrm, scene_col = obj, normals, colors
    if table:
        m = 3000
        z = transform_points(env_from_object, pts)[:, 2].min()
        xy = obj[:, :2].mean(axis=0) + rng.uniform(-0.7 * diam, 0.7 * diam, size=(m, 2))
        scene_pts = np.vstack([obj, np.column_stack([xy, np.full(m, z)])])
        scene_nrm = np.vstack([normals, np.tile(UP, (m, 1))])
        if colors is not None:
            scene_col = np.vstack([colors, np.full((m, 3), 0.6)])
    return SceneCloud.create(scene_pts, scene_nrm, scene_col), obj


def upright(yaw_deg: float, xyz: tuple[float, float, float], flip: bool = False) -> np.ndarray:
    r = axis_angle_matrix(UP, np.radians(yaw_deg))
    if flip:
        r = r @ axis_angle_matrix(np.array([1.0, 0.0, 0.0]), np.pi)
    return make_rigid(r, xyz)


# ---------------------------------------------------------------- geometry properties


def test_invert_rigid_round_trip_and_symmetric_error_properties() -> None:
    rng = np.random.default_rng(0)
    for _ in range(20):
        t = random_rigid(rng, 2.0)
        assert np.allclose(invert_rigid(t) @ t, np.eye(4), atol=1e-12)
        assert np.allclose(t @ invert_rigid(t), np.eye(4), atol=1e-12)
        assert np.allclose(t[:3, :3] @ t[:3, :3].T, np.eye(3), atol=1e-12)
        assert np.linalg.det(t[:3, :3]) == pytest.approx(1.0)
    from workers.pipeline.model.symmetry_group import SymmetrySpec, rotation_about

    turn = rotation_about(UP, np.pi / 2, np.zeros(3))
    spec = SymmetrySpec("discrete", (np.eye(4), turn, turn @ turn, turn @ turn @ turn))
    t = random_rigid(rng, 1.0)
    assert symmetric_pose_error(t @ turn, t, spec) == pytest.approx((0.0, 0.0), abs=1e-6)
    assert pose_error(t @ turn, t)[1] == pytest.approx(90.0)


# ---------------------------------------------------------------- oracle: known poses


def test_exclusion_counts_points_below_the_support_or_where_a_camera_saw_through() -> None:
    # a camera looking down at a floor (z = 0) it saw from 1 m to 2 m away
    k = np.array([[400.0, 0, 320], [0, 400, 240], [0, 0, 1]])
    cam = Camera("c", k, 640, 480, look_at((1.5, 0.0, 1.5), (0.0, 0.0, 0.0)))
    g = np.linspace(-0.6, 0.6, 241)
    floor = np.column_stack([np.repeat(g, len(g)), np.tile(g, len(g)), np.zeros(len(g) ** 2)])
    free_space = [render_depth(cam, floor.astype(np.float32))]
    support = np.array([0.0, 0.0, 1.0, 0.0])
    band = 0.004
    on = np.column_stack([np.linspace(-0.2, 0.2, 60), np.zeros(60), np.full(60, 0.002)])
    in_air = on + np.array([0.0, 0.0, 0.05])  # the camera saw the floor behind these: 5 cm in front
    sunk = on - np.array([0.0, 0.0, 0.05])  # below the support
    posed = np.concatenate([on, on, on, on, in_air, sunk])  # 4 : 1 : 1
    assert exclusion_factor(on, support, free_space, band) == 1.0
    assert exclusion_factor(in_air, None, free_space, band) == 0.0
    assert exclusion_factor(in_air, support, (), band) == 1.0  # no depth maps: no evidence
    assert exclusion_factor(posed, support, free_space, band) == pytest.approx(1 - 3 * 2 / 6)
    assert exclusion_factor(posed, support, (), band) == pytest.approx(1 - 3 * 1 / 6)
    # out of the camera's view nothing was seen: no evidence either
    far_off = in_air + np.array([0.0, 5.0, 0.0])
    assert exclusion_factor(far_off, None, free_space, band) == 1.0


def test_exclusion_needs_more_cameras_seeing_through_than_seeing_a_surface_there() -> None:
    """A real object in a sparse stretch of the cloud: one camera's z-buffer has a hole
    there and shows the floor behind, two others see the object's surface. That is a hole,
    not free space; seen through by two of three cameras, it is free space."""
    k = np.array([[400.0, 0, 320], [0, 400, 240], [0, 0, 1]])
    eyes = [(1.5, 0.0, 1.5), (-1.5, 0.0, 1.5), (0.0, 1.5, 1.5)]
    cams = [Camera(f"c{i}", k, 640, 480, look_at(e, (0.0, 0.0, 0.0))) for i, e in enumerate(eyes)]
    g = np.linspace(-0.6, 0.6, 241)
    floor = np.column_stack([np.repeat(g, len(g)), np.tile(g, len(g)), np.zeros(len(g) ** 2)])
    h = np.linspace(-0.1, 0.1, 81)
    top = np.column_stack([np.repeat(h, len(h)), np.tile(h, len(h)), np.full(len(h) ** 2, 0.05)])
    with_top = np.concatenate([floor, top]).astype(np.float32)
    probe = top[::50]
    support, band = np.array([0.0, 0.0, 1.0, 0.0]), 0.004
    holes = [render_depth(cams[0], floor.astype(np.float32))]
    holes += [render_depth(c, with_top) for c in cams[1:]]
    empty, there = depth_votes(probe, holes, band)
    assert empty.tolist() == [1] * len(probe) and there.tolist() == [2] * len(probe)
    assert exclusion_factor(probe, support, holes, band) == 1.0
    through = [render_depth(c, floor.astype(np.float32)) for c in cams[:2]] + holes[2:]
    assert exclusion_factor(probe, support, through, band) == 0.0


def test_a_pose_sunk_into_its_support_is_lifted_onto_it() -> None:
    rng = np.random.default_rng(0)
    box = rng.uniform([-0.05, -0.03, 0.0], [0.05, 0.03, 0.04], (500, 3))  # object frame
    box[0, 2] = 0.0  # its lowest point
    floor = np.array([0.0, 0.0, 1.0, -0.1])  # the plane z = 0.1 m, normal up
    g = np.linspace(-0.2, 0.2, 41)
    around = np.column_stack([np.repeat(g, 41) + 0.3, np.tile(g, 41) - 0.2, np.full(41**2, 0.1)])
    tilt = axis_angle_matrix(np.array([1.0, 1.0, 0.0]), np.radians(3.0))
    for sunk, lifted in ((0.004, True), (0.0095, True), (0.02, False), (-0.002, False)):
        pose = make_rigid(tilt, [0.3, -0.2, 0.0])
        pose[:3, 3] += [0, 0, 0.1 - transform_points(pose, box)[:, 2].min() - sunk]
        out = out_of_support(pose, box, floor, around, 0.01, 0.01)
        np.testing.assert_allclose(out[:3, :3], pose[:3, :3])  # only moved, along the normal
        np.testing.assert_allclose(out[:2, 3], pose[:2, 3])
        lowest = transform_points(out, box)[:, 2].min()
        assert lowest == pytest.approx(0.1 if lifted else 0.1 - sunk, abs=1e-12)
        # a plane with no point away from the object is its own face, not a floor
        underneath = around[np.abs(around[:, 0] - 0.3) < 0.04]
        underneath = underneath[np.abs(underneath[:, 1] + 0.2) < 0.02]
        assert out_of_support(pose, box, floor, underneath, 0.01, 0.01) is pose
    assert out_of_support(pose, box, None, around, 0.01, 0.01) is pose
    assert out_of_support(pose, box, floor, around, 0.0, 0.01) is pose
    # by default a fit sunk 15 mm (as mugs and hammers of the tuning inventory were) is lifted
    pose = make_rigid(tilt, [0.3, -0.2, 0.0])
    pose[:3, 3] += [0, 0, 0.1 - transform_points(pose, box)[:, 2].min() - 0.015]
    out = out_of_support(pose, box, floor, around, PoseOptions().max_sink_m, 0.01)
    assert transform_points(out, box)[:, 2].min() == pytest.approx(0.1, abs=1e-12)


@pytest.mark.parametrize("seed", [1, 2])
def test_random_pose_is_recovered(
    shared_data: Path, ycb_models: dict[str, PreparedModel], seed: int
) -> None:
    mesh = shared_data / "ycb" / "power_drill" / "textured.obj"
    true = random_rigid(np.random.default_rng(seed), 0.5)
    scene, obj = partial_view(mesh, true, seed, n_views=2, table=False)
    result = estimate_pose(ycb_models["power_drill"], scene, cluster_points_env=obj[::2])
    dt, dr = pose_error(result.env_from_object, true)
    assert dt < 0.005 and dr < 2.0, (dt, dr, result.trials)
    assert result.verified, result.rejections
    assert not result.ambiguous and result.equivalent_poses == ()
    assert result.fitness > 0.3 and result.inlier_rmse_m < 0.003
    assert result.env_from_object.dtype == np.float64 and result.env_from_object.shape == (4, 4)
    ransac = [t for t in result.trials if t.source.startswith("ransac") and "+" not in t.source]
    # seeds stop once two starts agree on the best candidate, after at least min_seeds
    default = POSE_PRESETS["default"]
    assert default.min_seeds <= len(ransac) <= default.n_seeds


def test_same_seed_same_pose(shared_data: Path, ycb_models: dict[str, PreparedModel]) -> None:
    mesh = shared_data / "ycb" / "power_drill" / "textured.obj"
    true = random_rigid(np.random.default_rng(5), 0.5)
    scene, obj = partial_view(mesh, true, 5, table=True)
    a = estimate_pose(ycb_models["power_drill"], scene, cluster_points_env=obj)
    b = estimate_pose(ycb_models["power_drill"], scene, cluster_points_env=obj)
    assert np.array_equal(a.env_from_object, b.env_from_object)
    assert [t.source for t in a.trials] == [t.source for t in b.trials]
    assert [t.score for t in a.trials] == [t.score for t in b.trials]
    for ta, tb in zip(a.trials, b.trials, strict=True):
        assert np.array_equal(ta.env_from_object, tb.env_from_object), ta.source


def test_feature_ransac_repeats_its_seed_on_one_thread(shared_data: Path) -> None:
    """Open3D's feature RANSAC on several threads draws a seed's sequence in another order
    each run (a partial drill: some seeds land elsewhere); on one thread it repeats, and the
    thread count is restored after."""
    reg = o3d.pipelines.registration
    pts, _, _ = load_surface(
        shared_data / "ycb" / "power_drill" / "textured.obj",
        ModelOptions(n_points=20000, sampling="uniform", seed=3),
    )
    v = 0.004
    model = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)).voxel_down_sample(v)
    m = np.asarray(model.points)
    part = m[m[:, 0] > np.median(m[:, 0]) - 0.01]
    rng = np.random.default_rng(0)
    scene_pts = transform_points(upright(40.0, (0.1, 0.2, 0.0)), part)
    scene = o3d.geometry.PointCloud(
        o3d.utility.Vector3dVector(scene_pts + rng.normal(0, 0.001, part.shape))
    )
    features = []
    for cloud in (scene, model):
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=3 * v, max_nn=30))
        features.append(
            reg.compute_fpfh_feature(
                cloud, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * v, max_nn=100)
            )
        )
    checkers = [
        reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
        reg.CorrespondenceCheckerBasedOnDistance(1.5 * v),
    ]

    def draws() -> list[np.ndarray]:
        out = []
        for seed in range(5):
            with seeded_open3d(1000 + seed):
                res = reg.registration_ransac_based_on_feature_matching(
                    scene,
                    model,
                    *features,
                    False,
                    1.5 * v,
                    reg.TransformationEstimationPointToPoint(False),
                    3,
                    checkers,
                    reg.RANSACConvergenceCriteria(20000, 0.999),
                )
            out.append(np.asarray(res.transformation))
        return out

    threads = o3d.utility.get_max_threads()
    first = draws()
    assert o3d.utility.get_max_threads() == threads
    for _ in range(2):
        for a, b in zip(first, draws(), strict=True):
            assert np.array_equal(a, b)


def test_previous_pose_is_an_extra_candidate(
    shared_data: Path, ycb_models: dict[str, PreparedModel]
) -> None:
    # a moved object: ICP from the previous pose (3 cm, 10° away) finds it even when no
    # RANSAC seed is run at all
    mesh = shared_data / "ycb" / "power_drill" / "textured.obj"
    true = random_rigid(np.random.default_rng(11), 0.5)
    scene, obj = partial_view(mesh, true, 11, n_views=2)
    previous = true @ make_rigid(
        axis_angle_matrix([1.0, 2.0, 0.5], np.radians(10)), [0.03, 0.0, 0.0]
    )
    options = replace(POSE_PRESETS["default"], n_seeds=0)
    result = estimate_pose(  # a centre only: no cluster-axes start either
        ycb_models["power_drill"],
        scene,
        centre_env=obj.mean(axis=0),
        previous_env_from_object=previous,
        options=options,
    )
    dt, dr = pose_error(result.env_from_object, true)
    assert dt < 0.005 and dr < 2.0
    assert result.source == "previous pose"


def test_a_moved_objects_previous_orientation_is_tried_on_its_cluster(
    shared_data: Path, ycb_models: dict[str, PreparedModel]
) -> None:
    """Moved 1.6 m and turned 110° on the same face: the previous pose itself is out of
    reach, but its orientation set on the cluster and turned about the up axis lies within
    15° and 2 cm of the truth, its lowest point on the cluster's; polished from these starts
    and the cluster's axes (no RANSAC seed), the pose is found. (The cluster's axes alone
    find this drill too: what the starts add is checked above.)"""
    model = ycb_models["power_drill"]
    mesh = shared_data / "ycb" / "power_drill" / "textured.obj"
    rest = np.asarray(model.points) @ UP
    true = upright(130.0, (0.9, 0.4, -float(rest.min())))
    previous = upright(20.0, (-0.7, 0.2, -float(rest.min())))
    scene, obj = partial_view(mesh, true, 5, n_views=2)
    inputs = check_inputs(obj, None, previous, UP)
    starts = previous_on_cluster(model, inputs, obj)
    assert len(starts) == PREVIOUS_TURNS
    lowest = [float(np.min(transform_points(s, model.points) @ UP)) for s in starts]
    np.testing.assert_allclose(lowest, float(np.min(obj @ UP)), atol=1e-9)
    dt, dr = min((pose_error(s, true) for s in starts), key=lambda e: e[1])
    assert dr < 15.0 and dt < 0.02, (dt, dr)
    options = replace(POSE_PRESETS["default"], n_seeds=0)
    result = estimate_pose(
        model, scene, cluster_points_env=obj, previous_env_from_object=previous, options=options
    )
    dt, dr = pose_error(result.env_from_object, true)
    assert dt < 0.005 and dr < 2.0, (dt, dr)


def test_an_added_object_is_tried_standing_as_the_library_gives_it(
    shared_data: Path, ycb_models: dict[str, PreparedModel]
) -> None:
    """Added, with no previous pose: the model standing on its library up, set on the
    cluster and turned about the up axis, gives a start within 15° and 2 cm of an upright
    truth, every start upright with its lowest point at the cluster's; an estimate with an
    upright previous pose tries no such start (its own turns stand the same way)."""
    model = ycb_models["power_drill"]
    mesh = shared_data / "ycb" / "power_drill" / "textured.obj"
    rest = np.asarray(model.points) @ UP
    true = upright(130.0, (0.9, 0.4, -float(rest.min())))
    scene, obj = partial_view(mesh, true, 5, n_views=2)
    starts = upright_on_cluster(model, check_inputs(obj, None, None, UP), obj)
    assert len(starts) == PREVIOUS_TURNS
    for s in starts:
        assert float(s[:3, :3] @ model.up_object @ UP) == pytest.approx(1.0, abs=1e-9)
        assert float(np.min(transform_points(s, model.points) @ UP)) == pytest.approx(
            float(np.min(obj @ UP)), abs=1e-9
        )
    dt, dr = min((pose_error(s, true) for s in starts), key=lambda e: e[1])
    assert dr < 15.0 and dt < 0.02, (dt, dr)
    assert upright_on_cluster(model, check_inputs(obj, None, None, UP), obj[:0]) == []
    options = replace(POSE_PRESETS["default"], n_seeds=0, max_rounds=1)
    added = estimate_pose(model, scene, cluster_points_env=obj, options=options)
    assert sum(t.source.startswith("upright turned") for t in added.trials) >= PREVIOUS_TURNS
    previous = upright(20.0, (-0.7, 0.2, -float(rest.min())))
    moved = estimate_pose(
        model, scene, cluster_points_env=obj, previous_env_from_object=previous, options=options
    )
    assert not any(t.source.startswith("upright turned") for t in moved.trials)


def test_flat_object_on_the_floor_from_the_top_of_its_cluster(
    shared_data: Path, tmp_path: Path
) -> None:
    # a hammer lying on a wide floor, seen from above; the change cluster is only its
    # upper half (a comparison threshold cuts the rest). The floor is removed before
    # registration and the cluster's principal axes give a start besides the descriptors
    # (measured: either alone suffices here; without both no candidate is found at all).
    mesh = shared_data / "ycb" / "hammer" / "textured.obj"
    model = prepare_model(mesh, tmp_path / "hammer")
    true = upright(70.0, (0.2, -0.1, 0.0))
    scene, obj = partial_view(
        mesh, true, 21, camera_dirs=[np.array([0.3, 0.2, 1.0]), np.array([-0.4, 0.1, 0.8])]
    )
    top = obj[obj[:, 2] > np.percentile(obj[:, 2], 50)]
    floor = np.column_stack(
        [np.random.default_rng(2).uniform(-0.3, 0.3, (20000, 2)) + true[:2, 3], np.zeros(20000)]
    )
    scene = SceneCloud.create(
        np.vstack([scene.points, floor]),
        np.vstack([scene.normals, np.tile(UP, (len(floor), 1))]),
    )
    result = estimate_pose(model, scene, cluster_points_env=top)
    dt, dr = pose_error(result.env_from_object, true)
    assert dt < 0.005 and dr < 2.0
    assert result.timings_s["support_removed"] > len(floor) / 2


# ---------------------------------------------------------------- symmetry


@pytest.mark.parametrize(
    ("name", "flip", "yaw"),
    [
        ("master_chef_can", False, 37.0),
        ("master_chef_can", True, 200.0),  # physically upside down: the flip is a symmetry
        ("wood_block", False, 123.0),
        ("wood_block", True, 10.0),
    ],
)
def test_symmetric_object_is_ambiguous_and_upside_down_only_by_its_colours(
    shared_data: Path, ycb_models: dict[str, PreparedModel], name: str, flip: bool, yaw: float
) -> None:
    model = ycb_models[name]
    true = upright(yaw, (0.3, -0.2, 0.05), flip=flip)
    scene, obj = partial_view(
        shared_data / "ycb" / name / "textured.obj",
        true,
        3,
        camera_dirs=[np.array([0.6, -0.3, 0.75])],
    )
    result = estimate_pose(model, scene, cluster_points_env=obj)
    # the wood grain breaks the block's symmetry: colour may choose among upright poses
    assert result.ambiguous and result.chosen_by in ("up", "colour")
    assert len(result.equivalent_poses) >= 1
    up_in_env = result.env_from_object[:3, :3] @ model.up_object
    if model.symmetry.kind == "continuous":
        # the can's label reads one way: its colours say which end is up, as it stands
        assert result.chosen_by == "colour" and (up_in_env @ UP > 0.99) == (not flip)
    else:
        assert up_in_env @ UP > 0.99  # upright within 8°, even when the true pose is flipped
    dt, dr = symmetric_pose_error(result.env_from_object, true, model.symmetry, model.centre_object)
    assert dt < 0.005 and dr < 2.0
    if result.chosen_by == "colour" and not flip and model.symmetry.kind == "discrete":
        # exact texture: colour finds the true pose
        dt, dr = pose_error(result.env_from_object, true)
        assert dt < 0.005 and dr < 2.0
    for eq in result.equivalent_poses:  # every reported equivalent fits as well
        e_t, e_r = symmetric_pose_error(eq, true, model.symmetry, model.centre_object)
        assert e_t < 0.005 and e_r < 2.0


def test_colour_chooses_among_upright_equivalents(
    shared_data: Path, ycb_models: dict[str, PreparedModel]
) -> None:
    # the mustard bottle's shape is symmetric under 180° about its axis (detected), its
    # label is not; at yaw 150° the smallest-rotation rule alone would pick yaw −30°
    model = ycb_models["mustard_bottle"]
    assert model.symmetry.kind == "discrete" and model.symmetry.appearance_breaks
    true = upright(150.0, (0.1, 0.4, 0.0))
    scene, obj = partial_view(
        shared_data / "ycb" / "mustard_bottle" / "textured.obj", true, 5, n_views=2
    )
    result = estimate_pose(model, scene, cluster_points_env=obj)
    assert result.ambiguous and result.chosen_by == "colour"
    dt, dr = pose_error(result.env_from_object, true)  # the true pose, not an equivalent
    assert dt < 0.005 and dr < 2.0
    grey = SceneCloud.create(scene.points, scene.normals, None)  # no colour: up decides
    assert estimate_pose(model, grey, cluster_points_env=obj).chosen_by == "up"


def test_an_equivalent_carried_by_an_inexact_symmetry_is_fitted_again(
    shared_data: Path, ycb_models: dict[str, PreparedModel], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A scanned model repeats only nearly: the group element that carries the fit to the
    equivalent colour chose may tilt and lift it (the bench's bleach bottle: 4.5° and 6 mm).
    Here every chosen equivalent comes 4° tilted and 5 mm up; it is a start, fitted again
    to the scan, and the pose published is the true one."""
    model = ycb_models["mustard_bottle"]
    true = upright(150.0, (0.1, 0.4, 0.0))
    scene, obj = partial_view(
        shared_data / "ycb" / "mustard_bottle" / "textured.obj", true, 5, n_views=2
    )
    off = make_rigid(axis_angle_matrix(np.array([1.0, 0.0, 0.0]), np.radians(4.0)), (0, 0, 0.005))
    real = pose_estimate_module.canonical_pose

    def inexact(pose: np.ndarray, *args: Any) -> Any:
        chosen = real(pose, *args)
        return replace(chosen, env_from_object=chosen.env_from_object @ off)

    monkeypatch.setattr(pose_estimate_module, "canonical_pose", inexact)
    result = estimate_pose(model, scene, cluster_points_env=obj)
    dt, dr = pose_error(result.env_from_object, true)
    assert dt < 0.003 and dr < 1.5, (dt, dr)
    assert result.verified, result.rejections
    for eq, s in zip(result.equivalent_poses, model.symmetry.rotations[1:], strict=True):
        np.testing.assert_allclose(eq, result.env_from_object @ s)


def test_cluster_coverage_tolerates_scan_noise_not_other_things(
    ycb_models: dict[str, PreparedModel],
) -> None:
    # a reconstructed cluster scatters 2–4 mm about the surface (measured on the generated
    # scenes): it must count as explained; a cluster that is 40 % something else must not
    model = ycb_models["power_drill"]
    rng = np.random.default_rng(3)
    options = POSE_PRESETS["default"]
    surface = model.points[rng.choice(len(model.points), 3000, replace=False)]
    noisy = surface + rng.normal(scale=0.003, size=surface.shape)
    identity = np.eye(4)
    assert cluster_coverage(noisy, model.points, identity, model.voxel_m, options) > 0.95
    blob = rng.normal(scale=0.01, size=(2000, 3)) + model.points.max(axis=0) + 0.03
    mixed = np.vstack([noisy, blob])
    assert cluster_coverage(mixed, model.points, identity, model.voxel_m, options) < 0.65


def test_scene_without_normals(shared_data: Path, ycb_models: dict[str, PreparedModel]) -> None:
    # a reconstructed cloud may come without normals: they are estimated and oriented
    # (away from the cluster, horizontal surfaces up) and the upright can is still found
    model = ycb_models["master_chef_can"]
    true = upright(75.0, (-0.4, 0.1, 0.02))
    scene, obj = partial_view(
        shared_data / "ycb" / "master_chef_can" / "textured.obj",
        true,
        8,
        camera_dirs=[np.array([-0.5, 0.4, 0.75])],
    )
    bare = SceneCloud.create(scene.points, colors=scene.colors)
    result = estimate_pose(model, bare, cluster_points_env=obj)
    dt, dr = symmetric_pose_error(result.env_from_object, true, model.symmetry)
    assert dt < 0.005 and dr < 2.0
    assert result.env_from_object[:3, :3] @ model.up_object @ UP > 0.99


def test_bowl_upside_down_is_reported_upside_down(
    shared_data: Path, ycb_models: dict[str, PreparedModel]
) -> None:
    # a bowl has no flip symmetry: canonicalisation must not "correct" a real flip
    model = ycb_models["bowl"]
    true = upright(0.0, (0.0, 0.0, 0.1), flip=True)
    scene, obj = partial_view(
        shared_data / "ycb" / "bowl" / "textured.obj",
        true,
        4,
        camera_dirs=[np.array([0.5, 0.2, 0.8])],
    )
    result = estimate_pose(model, scene, cluster_points_env=obj)
    assert result.ambiguous
    assert result.env_from_object[:3, :3] @ model.up_object @ UP < -0.99
    dt, dr = symmetric_pose_error(result.env_from_object, true, model.symmetry)
    assert dt < 0.005 and dr < 2.0


def test_a_mug_whose_opening_the_scan_closes_is_posed_upright_not_verified(
    shared_data: Path, tmp_path: Path
) -> None:
    """Stereo tends to close a mug's opening with a lid at the rim, which its closed bottom
    fits upside down about as well as its open top fits upright: the upright pose (the
    library gives a model resting on its base) is published, and not as verified."""
    mesh = shared_data / "ycb" / "mug" / "textured.obj"
    model = prepare_model(mesh, tmp_path / "mug")
    true = upright(30.0, (0.0, 0.0, 0.0))
    eyes = [(0.5 * np.cos(a), 0.5 * np.sin(a), 0.5) for a in np.radians([0, 90, 180, 270])]
    dirs = [np.array(e) - [0.0, 0.0, 0.04] for e in eyes]
    scene, obj = partial_view(mesh, true, 5, camera_dirs=dirs)
    rng = np.random.default_rng(5)
    base = model.points[model.points[:, 2] < model.points[:, 2].min() + 0.003]  # bottom disk
    axis_xy = transform_points(true, base.mean(axis=0, keepdims=True))[0, :2]
    rim = float(transform_points(true, model.points)[:, 2].max())
    # the opening closed at the rim; the cavity under it unseen
    lid_xy = axis_xy + rng.uniform(-0.036, 0.036, size=(3000, 2))
    lid_xy = lid_xy[np.linalg.norm(lid_xy - axis_xy, axis=1) < 0.036]
    lid = np.column_stack([lid_xy, rim - 0.004 + rng.normal(0, 0.001, len(lid_xy))])
    radius = np.linalg.norm(scene.points[:, :2] - axis_xy, axis=1)
    keep = ~((radius < 0.036) & (scene.points[:, 2] > 0.005))
    cavity = (np.linalg.norm(obj[:, :2] - axis_xy, axis=1) < 0.036) & (obj[:, 2] > 0.005)
    points = np.vstack([scene.points[keep], lid])
    normals = np.vstack([scene.normals[keep], np.tile(UP, (len(lid), 1))])
    cluster = np.vstack([obj[~cavity], lid])
    k = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    cams = [Camera(f"c{i}", k, 640, 480, look_at(e, (0.0, 0.0, 0.04))) for i, e in enumerate(eyes)]
    seen = [render_depth(c, points.astype(np.float32)) for c in cams]
    result = estimate_pose(
        model, SceneCloud.create(points, normals), cluster_points_env=cluster, free_space=seen
    )
    assert result.env_from_object[:3, :3] @ model.up_object @ UP > 0.9
    dt, dr = symmetric_pose_error(result.env_from_object, true, model.symmetry)
    assert dt < 0.01 and dr < 10.0
    assert not result.verified


def test_previous_pose_picks_the_nearest_equivalent(
    shared_data: Path, ycb_models: dict[str, PreparedModel]
) -> None:
    model = ycb_models["wood_block"]
    true = upright(20.0, (0.1, 0.1, 0.0))
    scene, obj = partial_view(
        shared_data / "ycb" / "wood_block" / "textured.obj", true, 6, n_views=2
    )
    quarter = model.symmetry.rotations[1]  # a 90° turn about the block's long axis
    previous = true @ quarter
    grey = SceneCloud.create(scene.points, scene.normals, None)  # no colour to tell them apart
    result = estimate_pose(model, grey, cluster_points_env=obj, previous_env_from_object=previous)
    assert result.chosen_by == "previous"
    dt, dr = pose_error(result.env_from_object, previous)
    assert dt < 0.005 and dr < 2.0
    # which quarter turn it is, grey gives no way to tell: a guess is never verified
    assert not result.verified
    assert any("symmetric equivalents" in r for r in result.rejections)


# ---------------------------------------------------------------- failures


def test_inputs_are_checked(ycb_models: dict[str, PreparedModel]) -> None:
    model = ycb_models["power_drill"]
    scene = SceneCloud.create(np.random.default_rng(0).uniform(-1, 1, size=(500, 3)))
    with pytest.raises(ShapeError):
        SceneCloud.create(np.zeros((10, 2)))
    with pytest.raises(ShapeError):
        SceneCloud.create(np.zeros((10, 3)), normals=np.zeros((9, 3)))
    with pytest.raises(InputError):
        estimate_pose(model, scene)  # neither cluster nor centre
    with pytest.raises(ShapeError):
        estimate_pose(model, scene, cluster_points_env=np.zeros((5, 4)))
    with pytest.raises(RegistrationError, match="scene points"):
        estimate_pose(model, scene, centre_env=[10.0, 10.0, 10.0])


# ---------------------------------------------------------------- real data


@pytest.fixture(scope="module")
def milk(
    shared_data: Path, tmp_path_factory: pytest.TempPathFactory
) -> tuple[PreparedModel, SceneCloud]:
    model = prepare_model(shared_data / "pcl" / "milk.pcd", tmp_path_factory.mktemp("milk"))
    # a single Kinect frame: normals oriented towards its camera at the origin
    scene = SceneCloud.from_file(
        shared_data / "pcl" / "milk_cartoon_all_small_clorox.pcd", viewpoint_env=(0.0, 0.0, 0.0)
    )
    return model, scene


@pytest.mark.parametrize("seed", [0, 1])
def test_milk_carton_in_real_kinect_scene(
    milk: tuple[PreparedModel, SceneCloud], seed: int
) -> None:
    model, scene = milk
    rng = np.random.default_rng(seed)
    env_from_kinect = random_rigid(rng, 1.0)  # the true env_from_object (model pose = identity)
    moved = SceneCloud.create(
        transform_points(env_from_kinect, scene.points),
        None if scene.normals is None else scene.normals @ env_from_kinect[:3, :3].T,
        scene.colors,
    )
    # the cluster centre is known only roughly: 2 cm off the carton's centre
    centre = transform_points(env_from_kinect, model.centre_object[None])[0] + rng.normal(
        scale=0.02, size=3
    )
    result = estimate_pose(model, moved, centre_env=centre)
    dt, dr = pose_error(result.env_from_object, env_from_kinect)
    assert dt < 0.005 and dr < 2.0
    assert result.verified, result.rejections


@dataclass(frozen=True)
class Outcome:
    """One pose estimate of the 3DMatch test: errors (m, degrees), right, verified."""

    case: str
    seed: int
    error_m: float
    error_deg: float
    right: bool
    verified: bool


def test_threedmatch_pair_verifies_only_right_poses(shared_data: Path, tmp_path: Path) -> None:
    """Real scans, three seeds each. Hard: the source scan against the reference scan (33 %
    overlap), where a wrong pose must never be flagged verified. Easy: the same reference
    with the source scan itself placed at the true pose, which verification must accept.
    Every verified pose is right, and at least half of the six trials (all the easy ones)
    are verified, so a check that never verifies fails here."""
    d = shared_data / "threedmatch_pair"
    src, ref, ref_from_src = (np.load(d / f) for f in ("src.npy", "ref.npy", "gt.npy"))
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src))
    o3d.io.write_point_cloud(tmp_path / "src.ply", cloud)
    model = prepare_model(tmp_path / "src.ply", tmp_path / "model")
    placed = transform_points(ref_from_src, src)
    cases = {
        "hard": (SceneCloud.create(ref), ref.mean(axis=0)),
        "easy": (SceneCloud.create(np.vstack([ref, placed])), placed.mean(axis=0)),
    }
    outcomes: list[Outcome] = []
    for case, (scene, centre) in cases.items():
        for seed in range(5):
            # one round per seed: the seeds themselves are the repetitions here
            options = PoseOptions(seed=seed, crop_factor=1.5, max_rounds=1)
            result = estimate_pose(model, scene, centre_env=centre, options=options)
            dt, dr = pose_error(result.env_from_object, ref_from_src)
            right = dt < 0.10 and dr < 5.0
            outcomes.append(Outcome(case, seed, round(dt, 3), round(dr, 2), right, result.verified))
    verified = [o for o in outcomes if o.verified]
    assert all(o.right for o in verified), outcomes  # every verified pose is right
    assert len(verified) >= len(outcomes) / 2, outcomes
    assert all(o.verified for o in outcomes if o.case == "easy"), outcomes


def test_pose_cli(
    milk: tuple[PreparedModel, SceneCloud], shared_data: Path, tmp_path: Path
) -> None:
    model, _ = milk
    work = tmp_path / "milk"
    prepare_model(shared_data / "pcl" / "milk.pcd", work)
    centre = ",".join(f"{x:.4f}" for x in model.centre_object)
    scene = shared_data / "pcl" / "milk_cartoon_all_small_clorox.pcd"
    out = tmp_path / "out.txt"
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = pipeline_main(
            ["pose", "--model", str(work), "--scene", str(scene), f"--center={centre}"]
        )
    assert code == 0
    out.write_text(buf.getvalue())
    pose = np.asarray(json.loads(buf.getvalue())["env_from_object"])
    dt, dr = pose_error(pose, np.eye(4))
    assert dt < 0.005 and dr < 2.0


def test_a_cloud_file_without_normals_leaves_their_orientation_to_the_crop(tmp_path: Path) -> None:
    """Without a viewpoint, normals missing from the file are left to the crop (a room's
    origin is no camera to orient them towards); with one, they face it."""
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(-1, 1, (500, 2)), np.zeros(500)]
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    path = tmp_path / "floor.ply"
    o3d.io.write_point_cloud(str(path), pcd)
    assert SceneCloud.from_file(path).normals is None
    below = SceneCloud.from_file(path, viewpoint_env=(0.0, 0.0, -2.0))
    assert below.normals is not None and np.all(below.normals[:, 2] < -0.99)


def test_a_nearly_resting_object_is_turned_flat_onto_its_nearest_hull_face() -> None:
    rng = np.random.default_rng(1)
    box = rng.uniform([-0.1, -0.04, 0.0], [0.1, 0.04, 0.02], (2000, 3))  # a flat bar
    corners = np.array([[x, y, z] for x in (-0.1, 0.1) for y in (-0.04, 0.04) for z in (0, 0.02)])
    box = np.vstack([box, corners])
    faces = hull_normals(box, box.mean(axis=0))
    assert len(faces) == 6  # a box rests on any of its six faces
    lean = axis_angle_matrix(np.array([1.0, 0.3, 0.0]), np.radians(3.0))
    yaw = axis_angle_matrix(UP, np.radians(40.0))
    turn = resting_turn(lean @ yaw, faces[:0], faces, UP, 5.0)
    assert turn is not None
    np.testing.assert_allclose(turn @ lean @ yaw, yaw, atol=1e-9)  # flat again, yaw kept
    assert (
        resting_turn(
            axis_angle_matrix(np.array([1.0, 0, 0]), np.radians(8.0)), faces[:0], faces, UP, 5.0
        )
        is None
    )
    # the base the library gives first (2° off the bar's hull face), the hull faces after
    base = axis_angle_matrix(np.array([0.0, 1.0, 0]), np.radians(2.0)) @ np.array([0, 0, -1.0])
    on_base = resting_turn(yaw, base[None, :], faces, UP, 5.0)
    assert on_base is not None
    assert (on_base @ yaw @ base)[2] == pytest.approx(-1.0)
    # upside down on its top face is at rest too
    over = axis_angle_matrix(np.array([1.0, 0, 0]), np.pi + np.radians(2.0))
    turned = resting_turn(over, faces[:0], faces, UP, 5.0)
    assert turned is not None
    assert (turned @ over @ np.array([0, 0, 1.0]))[2] == pytest.approx(-1.0)


def test_a_rounded_object_rests_only_on_faces_that_hold_its_centre_above_them() -> None:
    """A dome (half a sphere on its flat base): its curved flank's hull slivers would tip it
    over, so turned 12° it goes back onto its base, not onto the sliver beneath it."""
    rng = np.random.default_rng(2)
    d = rng.normal(size=(4000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d[:, 2] = np.abs(d[:, 2])
    disc = rng.uniform(-1, 1, (3000, 2))
    disc = disc[np.linalg.norm(disc, axis=1) <= 1]
    dome = 0.08 * np.vstack([d, np.column_stack([disc, np.zeros(len(disc))])])
    centre = np.array([0.0, 0.0, 3 / 8 * 0.08])  # a solid half ball's centre of mass
    faces = hull_normals(dome, centre)
    # its base, and slivers within a few degrees of its crown (it rocks there, upside down)
    assert faces[:, 2].min() == pytest.approx(-1.0, abs=1e-6)
    assert np.all((faces[:, 2] < -0.9999) | (faces[:, 2] > np.cos(np.radians(10.0))))
    tilt = axis_angle_matrix(np.array([0.6, 0.8, 0.0]), np.radians(12.0))
    every = ConvexHull(dome).equations[:, :3]
    # a sliver of the hull lies nearer flat than the base
    assert np.max(every @ tilt.T @ -UP) > np.cos(np.radians(10.0))
    turn = resting_turn(tilt, faces[:0], faces, UP, 15.0)
    assert turn is not None
    np.testing.assert_allclose(turn @ tilt, np.eye(3), atol=1e-6)


def test_the_fit_on_a_plane_turns_about_its_normal_and_shifts_across_it_only() -> None:
    """A closed bar's scan (top, both sides, both ends), the start 1 cm off, 5 mm high and
    turned 4° about z: the plane fit recovers the turn and the shift across the plane and
    keeps the start's height and tilt, for every seed. (A bar with one side and no ends
    leaves its long axis free and its held height pulls the top's edge onto that side.)"""
    for seed in range(5):
        rng = np.random.default_rng(seed)
        top = np.column_stack(
            [rng.uniform(-0.1, 0.1, 3000), rng.uniform(-0.04, 0.04, 3000), np.full(3000, 0.02)]
        )
        side = np.column_stack(
            [rng.uniform(-0.1, 0.1, 800), np.full(800, -0.04), rng.uniform(0, 0.02, 800)]
        )
        end = np.column_stack(
            [np.full(400, -0.1), rng.uniform(-0.04, 0.04, 400), rng.uniform(0, 0.02, 400)]
        )
        half = np.vstack([side, end])  # the other side and end: turned half a turn about z
        half_n = np.vstack([np.tile([0, -1.0, 0], (800, 1)), np.tile([-1.0, 0, 0], (400, 1))])
        pts = np.vstack([top, half, half * [-1, -1, 1]])
        nrm = np.vstack([np.tile([0, 0, 1.0], (3000, 1)), half_n, half_n * [-1, -1, 1]])
        true = make_rigid(axis_angle_matrix(UP, np.radians(30.0)), [0.5, 0.2, 0.0])
        scan = transform_points(true, pts[::3]) + rng.normal(0, 0.0005, (len(pts[::3]), 3))
        start = make_rigid(axis_angle_matrix(UP, np.radians(34.0)), [0.51, 0.2, 0.005])
        fitted, _ = fit_scene_to_model(
            ModelSurface(pts, nrm), scan, start, 0.03, 50, plane_normal=UP
        )
        np.testing.assert_allclose(fitted[:3, 3], [0.5, 0.2, 0.005], atol=5e-4)
        assert pose_error(fitted, start)[1] == pytest.approx(4.0, abs=0.2)
        np.testing.assert_allclose(fitted[:3, :3] @ UP, UP, atol=1e-9)


def test_the_support_plane_is_refitted_on_the_whole_floor_not_a_ransac_band() -> None:
    """A 30 cm floor crop with 2 mm noise, tilted 0.3°: the plane comes out within 0.15° of
    it for every seed (three noisy points and a band narrower than the noise kept their
    tilt: up to 0.42°, median 0.2°)."""
    tilt = np.radians(0.3)
    true_n = np.array([-np.sin(tilt), 0.0, np.cos(tilt)])
    for seed in range(10):
        rng = np.random.default_rng(seed)
        xy = rng.uniform(-0.15, 0.15, (2000, 2))
        floor = np.column_stack([xy, xy[:, 0] * np.tan(tilt) + rng.normal(0, 0.002, 2000)])
        plane = support_plane(
            floor, np.tile(UP, (2000, 1)), UP, np.array([[0, 0, 0.05]]), 0.0025, seed
        )
        assert plane is not None
        assert np.degrees(np.arccos(min(1.0, plane[:3] @ true_n))) < 0.15


def test_the_score_leaves_out_what_rests_on_the_support_and_faces_it() -> None:
    """A cup's base, on the floor and facing it, is never seen: the fine score leaves it out
    (and the points within the support band), so upright and upside down are judged by
    what a camera could see; its walls and a face up in the air count."""
    from types import SimpleNamespace

    from workers.pipeline.pose.refine import Refiner

    base = np.column_stack([np.zeros((50, 2)), np.full(50, 0.004)])  # 4 mm up, facing down
    wall = np.column_stack([np.zeros((50, 2)), np.linspace(0.02, 0.1, 50)])  # facing out
    high = np.column_stack([np.zeros((50, 2)), np.full(50, 0.06)])  # a handle's underside
    points = np.vstack([base, wall, high])
    normals = np.vstack([np.tile([0, 0, -1.0], (50, 1)), np.tile([1.0, 0, 0], (50, 1))] * 1)
    normals = np.vstack([normals, np.tile([0, 0, -1.0], (50, 1))])
    region = SimpleNamespace(support=np.array([0.0, 0.0, 1.0, 0.0]), band_m=0.002)
    ctx = SimpleNamespace(region=region, model=SimpleNamespace(voxel_m=0.005))
    refiner = Refiner(ctx, points, normals, None, np.zeros((0, 3)), np.zeros((0, 3)))
    seen = points[refiner._in_view(points, normals, np.eye(3))]
    assert len(seen) == 100 and seen[:, 2].min() >= 0.02
    region.support = None
    assert np.count_nonzero(refiner._in_view(points, normals, np.eye(3))) == 150


def cup_base_and_wall() -> tuple[np.ndarray, np.ndarray]:
    """(100, 3) points and outward normals of a cup resting on z = 0: its base 4 mm up
    facing down (50 points, first), then its wall facing out, 2-10 cm up (50)."""
    base = np.column_stack([np.zeros((50, 2)), np.full(50, 0.004)])
    wall = np.column_stack([np.zeros((50, 2)), np.linspace(0.02, 0.1, 50)])
    normals = np.vstack([np.tile([0, 0, -1.0], (50, 1)), np.tile([1.0, 0, 0], (50, 1))])
    return np.vstack([base, wall]), normals


def test_the_refining_icp_fits_only_what_the_score_counts(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The cup's base, resting on the floor and facing it, has no scan to pair with: the
    refining ICP leaves it out at every scale, as the score does."""
    from types import SimpleNamespace

    from workers.pipeline.pose import refine
    from workers.pipeline.pose.result import Trial

    points, normals = cup_base_and_wall()
    wall = points[50:]
    region = SimpleNamespace(
        support=np.array([0.0, 0.0, 1.0, 0.0]),
        band_m=0.002,
        target_fine=SimpleNamespace(tree=cKDTree(wall)),
    )
    options = SimpleNamespace(
        icp_scales_voxels=(1.5, 0.6), icp_max_iterations=5, fine_score_voxels=1.0
    )
    ctx = SimpleNamespace(
        region=region,
        model=SimpleNamespace(voxel_m=0.005),
        options=options,
        exclusion=lambda posed: 1.0,
    )
    fitted: list[np.ndarray] = []

    def icp(src, src_normals, target, init, dist, iters):  # type: ignore[no-untyped-def]
        fitted.append(src)
        return init

    monkeypatch.setattr(refine, "icp_point_to_plane", icp)
    refiner = refine.Refiner(ctx, points, normals, None, np.zeros((0, 3)), np.zeros((0, 3)))
    refiner._refine(Trial("start", 0.0, 0.0, 0.0, 0.0, np.eye(4)))
    assert len(fitted) == 2
    assert all(len(src) == 50 and src[:, 2].min() >= 0.02 for src in fitted)


def test_the_finishing_icp_fits_only_what_a_camera_could_see(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The finishing ICP, on every model point, leaves out the cup's base resting on the
    floor as the refining ICP does."""
    from types import SimpleNamespace

    from workers.pipeline.pose import refine
    from workers.pipeline.pose.result import Trial

    points, normals = cup_base_and_wall()
    wall = points[50:]
    region = SimpleNamespace(support=np.array([0.0, 0.0, 1.0, 0.0]), band_m=0.002, target_fine=wall)
    options = SimpleNamespace(icp_scales_voxels=(1.5, 0.6), icp_max_iterations=5)
    model = SimpleNamespace(voxel_m=0.005, points=points, normals=normals)
    ctx = SimpleNamespace(region=region, model=model, options=options)

    class Fitted(Exception):
        pass

    def icp(src, src_normals, target, init, dist, iters):  # type: ignore[no-untyped-def]
        raise Fitted(src)

    monkeypatch.setattr(refine, "icp_point_to_plane", icp)
    refiner = refine.Refiner(ctx, points, normals, None, np.zeros((0, 3)), np.zeros((0, 3)))
    refined = refine.Refined(0.5, np.eye(4), Trial("start", 0.0, 0.0, 0.0, 0.0, np.eye(4)))
    with pytest.raises(Fitted) as fitted:
        refiner._finish(refined)
    src = fitted.value.args[0]
    assert len(src) == 50 and src[:, 2].min() >= 0.02


def test_the_score_counts_what_a_pose_sinks_below_the_support() -> None:
    """Model points half a band or more under the support plane are not hidden by it (the
    support's own points lie within half a band of it): a pose tilted into the floor
    cannot raise its score by burying what it fails to explain."""
    from types import SimpleNamespace

    from workers.pipeline.pose.refine import Refiner

    band = 0.004
    heights = (-0.004, -0.0025, -0.0015, 0.003)  # sunk, sunk, within the support's noise, in band
    points = np.column_stack([np.zeros((4, 2)), heights])
    normals = np.tile([1.0, 0.0, 0.0], (4, 1))
    region = SimpleNamespace(support=np.array([0.0, 0.0, 1.0, 0.0]), band_m=band)
    ctx = SimpleNamespace(region=region, model=SimpleNamespace(voxel_m=0.005))
    points, normals = np.repeat(points, 5, axis=0), np.repeat(normals, 5, axis=0)
    refiner = Refiner(ctx, points, normals, None, np.zeros((0, 3)), np.zeros((0, 3)))
    seen = points[refiner._in_view(points, normals, np.eye(3))]
    assert sorted(set(np.round(seen[:, 2], 4))) == [-0.004, -0.0025]


def wrench_from_above(shared_data: Path, tmp_path: Path) -> tuple[Refiner, np.ndarray, np.ndarray]:
    """A refiner of an adjustable wrench lying on the floor seen from above (three cameras,
    its smeared scan and 1.5 mm noisy floor), its true pose and that pose turned over about
    the wrench's length (its other face up: upside down)."""
    from workers.pipeline.pose.candidates import FitContext
    from workers.pipeline.pose.crop import check_inputs, crop_scene

    mesh = shared_data / "ycb" / "adjustable_wrench" / "textured.obj"
    model = prepare_model(mesh, tmp_path / "wrench")
    true = upright(30.0, (0.0, 0.0, 0.0))
    true[2, 3] -= transform_points(true, model.points)[:, 2].min()
    dirs = [np.array([np.cos(a), np.sin(a), 1.2]) for a in (0.3, 2.4, 4.4)]
    scene, obj = partial_view(mesh, true, 3, camera_dirs=dirs, table=False)
    rng = np.random.default_rng(3)
    floor = np.column_stack([rng.uniform(-0.25, 0.25, (20000, 2)), rng.normal(0, 0.0015, 20000)])
    scene = SceneCloud.create(
        np.vstack([obj, floor]), np.vstack([scene.normals, np.tile(UP, (len(floor), 1))])
    )
    options = POSE_PRESETS["default"]
    inputs = check_inputs(obj[obj[:, 2] > 0.0045], None, None, UP)
    refiner = Refiner.create(
        FitContext(model, crop_scene(model, scene, inputs, options), (), options, inputs.up)
    )
    centred = model.points - model.centre_object
    long_axis = np.linalg.eigh(centred.T @ centred)[1][:, 2]
    over = 2.0 * np.outer(long_axis, long_axis) - np.eye(3)  # 180° about its length
    upside_down = true @ make_rigid(over, model.centre_object - over @ model.centre_object)
    return refiner, true, upside_down


def test_an_upside_down_winner_is_also_tried_upright(shared_data: Path, tmp_path: Path) -> None:
    """A flat object's smeared scan can fit its other face best from every start; when the
    best refined pose is upside down, its turns that stand it upright are refined too, and
    the true pose among them wins on the scan (an adjustable wrench seen from above)."""
    from workers.pipeline.pose.refine import Refined
    from workers.pipeline.pose.result import Trial

    refiner, true, upside_down = wrench_from_above(shared_data, tmp_path)
    model = refiner.ctx.model
    refiner.refined = [Refined(1.0, upside_down, Trial("given", 1.0, 0.5, 0.001, 0.0, upside_down))]
    refiner._turn_upright()
    turned = [r for r in refiner.refined if refiner.ctx.upright(r.env_from_object)]
    assert turned and len(refiner.refined) == 1 + len(turned)
    best = max(turned, key=lambda r: r.score)
    dt, dr = symmetric_pose_error(best.env_from_object, true, model.symmetry, model.centre_object)
    assert dt < 0.005 and dr < 2.0
    assert best.score > refiner.score(upside_down)
    refiner._turn_upright()  # once per pose
    assert len(refiner.refined) == 1 + len(turned)


@pytest.mark.parametrize(("upright_score", "takes_upright"), [(0.75, True), (0.65, False)])
def test_an_upside_down_best_gives_way_to_an_upright_pose_within_upright_ratio(
    shared_data: Path, tmp_path: Path, upright_score: float, takes_upright: bool
) -> None:
    """The scan tells an object's up from its down only weakly (stereo closes a mug's
    opening, which its base fits upside down): an upright pose resting on the support that
    scores at least ``upright_ratio`` (0.7) × an upside-down best wins; one scoring less
    does not."""
    from workers.pipeline.pose.candidates import CandidatePool
    from workers.pipeline.pose.refine import Refined
    from workers.pipeline.pose.result import Trial

    refiner, true, upside_down = wrench_from_above(shared_data, tmp_path)
    assert refiner.ctx.options.upright_ratio == 0.7
    refiner.refined = [
        Refined(1.0, upside_down, Trial("down", 1.0, 0.5, 0.001, 0.0, upside_down)),
        Refined(upright_score, true, Trial("up", upright_score, 0.5, 0.001, 0.0, true)),
    ]
    winner = refiner._winner()
    assert (winner.env_from_object is true) == takes_upright
    assert (winner.env_from_object is upside_down) == (not takes_upright)
    # the round that publishes it says whether the rule stood it up against the scan
    refiner.turned_ids = {id(r) for r in refiner.refined}  # no upright turns added
    fit = refiner.round(CandidatePool(refiner.ctx, None))  # type: ignore[arg-type]
    assert fit.righted == takes_upright


def test_near_ties_are_finished_as_the_winner_and_a_flat_ones_outline_settles_them(
    shared_data: Path, tmp_path: Path
) -> None:
    """The wrench from above with two near-ties of its true pose: the same pose turned 6°
    (distinct as refined; finished as the winner is, it comes to the winner's pose: no
    rival) and its other face up (distinct either way: its outline is the mirror image
    and leaves the scan's points outside it, so the outline settles the tie). With the
    outline off, the other face stays the runner-up; given the other face as the winner,
    the outline chooses the true pose. The near-ties are handed on finished."""
    from workers.pipeline.pose.candidates import CandidatePool
    from workers.pipeline.pose.refine import Refined
    from workers.pipeline.pose.result import Trial

    refiner, true, upside_down = wrench_from_above(shared_data, tmp_path)
    model = refiner.ctx.model
    centre = transform_points(true, model.centre_object[None])[0]
    spun = (
        make_rigid(
            axis_angle_matrix(UP, np.radians(6.0)),
            centre - axis_angle_matrix(UP, np.radians(6.0)) @ centre,
        )
        @ true
    )

    def refined(score: float, pose: np.ndarray) -> Refined:
        return Refined(score, pose, Trial("given", score, 0.5, 0.001, 0.0, pose))

    pool = CandidatePool(refiner.ctx, None)  # type: ignore[arg-type]
    for ratio, settles in ((0.0, False), (refiner.ctx.options.outline_settle_ratio, True)):
        refiner.ctx = replace(
            refiner.ctx, options=replace(refiner.ctx.options, outline_settle_ratio=ratio)
        )
        refiner.finished = {}
        refiner.refined = [refined(1.0, true), refined(0.97, spun), refined(0.95, upside_down)]
        fit = refiner.round(pool)
        assert pose_error(fit.env_from_object, true)[1] < 2.0
        if settles:
            assert fit.runner_up == 0.0 and fit.settled_by_outline is not None
            cost, rival = fit.settled_by_outline
            assert rival > ratio * cost
        else:
            assert fit.runner_up == 0.95 and fit.settled_by_outline is None
        # the spun near-tie, finished, came to the winner's pose
        spun_done = refiner.finished[id(refiner.refined[1])].env_from_object
        assert pose_error(spun_done, fit.env_from_object)[1] < 1.0
        assert [r.score for r in fit.others] == [0.97, 0.95]
        assert not fit.righted  # the best pose won
        # and is handed on at its finished pose, as every near-tie is
        assert all(
            r.env_from_object is refiner.finished[id(r0)].env_from_object
            for r, r0 in zip(fit.others, refiner.refined[1:], strict=True)
        )
    winner, mirrored = (
        refiner.finished[id(refiner.refined[0])],
        refiner.finished[id(refiner.refined[2])],
    )
    settled = refiner._by_outline([mirrored, winner])
    assert settled is not None and settled[0] is winner


@pytest.mark.parametrize("seed", [1, 2, 3, 4])
def test_colour_reads_the_texture_through_the_shading(
    shared_data: Path, ycb_models: dict[str, PreparedModel], seed: int
) -> None:
    """The wood block lit by one light (each face shaded by its direction, as a render or a
    room lamp does): the true pose's colours agree best among its upright equivalents, by
    at least 0.05 (with the means removed over the whole object the shading decided, and
    the true pose came out best in none of these four)."""
    from workers.pipeline.model import make_cloud
    from workers.pipeline.pose.canonical import colour_agreement
    from workers.pipeline.pose.fit import Target

    model = ycb_models["wood_block"]
    true = upright(25.0 + 40 * seed, (0.1, 0.1, 0.0))
    scene, _ = partial_view(
        shared_data / "ycb" / "wood_block" / "textured.obj", true, seed, n_views=3, table=False
    )
    light = np.array([0.4, 0.25, 1.0]) / np.linalg.norm([0.4, 0.25, 1.0])
    shade = 0.35 + 0.75 * np.clip(scene.normals @ light, 0, None)
    lit = Target(
        make_cloud(scene.points, scene.normals, np.clip(scene.colors * shade[:, None], 0, 1))
    )
    agreements = [
        colour_agreement(model, true @ s, lit, 0.003)
        for s in model.symmetry.rotations
        if (true @ s)[:3, :3] @ model.up_object @ UP > 0.9
    ]
    assert np.isclose(model.symmetry.rotations[0], np.eye(4)).all()
    assert agreements[0] >= max(agreements[1:]) + 0.05


DrillOnTable = tuple[PreparedModel, SceneCloud, np.ndarray, np.ndarray]


@pytest.fixture
def drill_on_table(shared_data: Path, ycb_models: dict[str, PreparedModel]) -> DrillOnTable:
    """The drill standing on a table seen from three sides: its model, the scene, the
    drill's own scan points (env frame) and its true env_from_object."""
    mesh = shared_data / "ycb" / "power_drill" / "textured.obj"
    true = upright(35.0, (0.2, -0.1, 0.0))
    dirs = [np.array([1.0, 0.2, 0.8]), np.array([-0.6, 0.9, 0.7]), np.array([-0.3, -1.0, 0.6])]
    scene, obj = partial_view(mesh, true, 3, camera_dirs=dirs)
    return ycb_models["power_drill"], scene, obj, true


def test_a_refit_on_the_support_that_turns_the_pose_far_leaves_it_unverified(
    drill_on_table: DrillOnTable, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The drill standing on a table, verified; when the refit on the support (the fit
    restricted to the plane) turns the pose by 4° (the scan does not hold that turn), the
    pose is unverified, naming the turn, and stays the one set flat: the turned refit
    explains fewer model points (its fitness is lower). The drill on its base, a quarter
    of its diameter tall, counts as flat: the fit of its outline seen from above is off
    here, where the point-to-plane refit is under test."""
    from workers.pipeline.pose import refine

    model, scene, obj, true = drill_on_table
    refit_only = replace(POSE_PRESETS["default"], top_view_max_height_ratio=0.0)
    held = estimate_pose(model, scene, cluster_points_env=obj, options=refit_only)
    assert held.verified, held.rejections
    assert pose_error(held.env_from_object, true)[1] < 2.0

    real_fit = refine.fit_scene_to_model

    def turning_fit(*args: object, **kwargs: object) -> tuple[np.ndarray, np.ndarray]:
        pose, weights = real_fit(*args, **kwargs)  # type: ignore[arg-type]
        if kwargs.get("plane_normal") is None:
            return pose, weights
        centre = pose[:3, :3] @ model.centre_object + pose[:3, 3]
        turn = axis_angle_matrix(UP, np.radians(4.0))
        turned = np.eye(4)
        turned[:3, :3] = turn @ pose[:3, :3]
        turned[:3, 3] = turn @ (pose[:3, 3] - centre) + centre
        return turned, weights

    monkeypatch.setattr(refine, "fit_scene_to_model", turning_fit)
    turned = estimate_pose(model, scene, cluster_points_env=obj, options=refit_only)
    assert not turned.verified
    assert any(r.startswith("the last fit turned the ICP pose by 4.") for r in turned.rejections)
    # pose_quality carries the figures behind the verdict
    figures = turned.quality_json()
    assert figures["verified"] is False and 3.9 < figures["final_turn_deg"] < 4.1
    assert pose_error(turned.env_from_object, true)[1] < 2.0
    assert turned.fitness > held.fitness - 0.05
    held_figures = held.quality_json()
    assert held_figures["cluster_coverage"] == held.cluster_coverage >= 0.85
    assert held_figures["runner_up_ratio"] <= 0.85 and held_figures["final_turn_deg"] <= 3.0


def test_a_refit_on_the_support_that_raises_the_fitness_is_kept(
    drill_on_table: DrillOnTable, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The drill standing on a table, its pose turned 5° about the table's normal before it
    is set flat (as a tall object's fits can leave it): the refit on the support turns it
    back, explains more of the scan, and is kept; unverified, naming the turn. With the fit
    of its outline seen from above (the drill counts as flat), that fit turns it back."""
    from workers.pipeline.pose import refine

    model, scene, obj, true = drill_on_table
    real_out_of_support = refine.out_of_support

    def turned(pose: np.ndarray, *args: object) -> np.ndarray:
        pose = real_out_of_support(pose, *args)
        centre = pose[:3, :3] @ model.centre_object + pose[:3, 3]
        turn = axis_angle_matrix(UP, np.radians(5.0))
        out = np.eye(4)
        out[:3, :3] = turn @ pose[:3, :3]
        out[:3, 3] = turn @ (pose[:3, 3] - centre) + centre
        return out

    monkeypatch.setattr(refine, "out_of_support", turned)
    refit_only = replace(POSE_PRESETS["default"], top_view_max_height_ratio=0.0)
    for options in (refit_only, POSE_PRESETS["default"]):
        result = estimate_pose(model, scene, cluster_points_env=obj, options=options)
        assert pose_error(result.env_from_object, true)[1] < 2.0
        assert not result.verified
        assert any(r.startswith("the last fit turned the ICP pose by") for r in result.rejections)


@pytest.mark.parametrize("tilt_deg", [6.0, 15.0, 30.0])
def test_a_pose_tipping_on_its_support_is_set_down_and_beyond_the_window_unverified(
    drill_on_table: DrillOnTable, monkeypatch: pytest.MonkeyPatch, tilt_deg: float
) -> None:
    """The drill standing on a table, its fitted pose tilted about a level axis and lowered
    until it touches the table on an edge of its base (as a hollow bowl's scan tilts it):
    within the rest window (10°) it is set flat and stays verifiable; beyond it, up to
    ``max_set_down_tilt_deg`` (20°), it is set down on its base all the same, right again,
    and unverified, naming the tilt; tilted further, something holds it: kept."""
    from workers.pipeline.pose import refine
    from workers.pipeline.pose.fit import lowest_height

    model, scene, obj, true = drill_on_table
    real_out_of_support = refine.out_of_support

    def tipping(
        pose: np.ndarray, points: np.ndarray, support: np.ndarray, *args: object
    ) -> np.ndarray:
        pose = real_out_of_support(pose, points, support, *args)
        centre = pose[:3, :3] @ model.centre_object + pose[:3, 3]
        turn = axis_angle_matrix(np.array([0.6, 0.8, 0.0]), np.radians(tilt_deg))
        tipped = make_rigid(turn @ pose[:3, :3], turn @ (pose[:3, 3] - centre) + centre)
        tipped[:3, 3] -= lowest_height(transform_points(tipped, points), support) * support[:3]
        return tipped

    monkeypatch.setattr(refine, "out_of_support", tipping)
    result = estimate_pose(model, scene, cluster_points_env=obj)
    dt, dr = pose_error(result.env_from_object, true)
    tipped = [r for r in result.rejections if "nothing it could rest on" in r]
    if tilt_deg > 20.0:
        assert not tipped and dr == pytest.approx(tilt_deg, abs=2.0)
        return
    assert dt < 0.005 and dr < 2.0, (dt, dr)
    if tilt_deg < 10.0:
        assert not tipped
    else:
        assert not result.verified and len(tipped) == 1
        assert f"turned by {tilt_deg:.1f}°" in tipped[0]
        # a bound at or below the rest window turns the setting down off
        off = replace(POSE_PRESETS["default"], max_set_down_tilt_deg=10.0)
        kept = estimate_pose(model, scene, cluster_points_env=obj, options=off)
        assert pose_error(kept.env_from_object, true)[1] == pytest.approx(tilt_deg, abs=2.0)


def test_a_small_objects_fitness_follows_the_scans_spacing(
    shared_data: Path, tmp_path: Path
) -> None:
    """A Rubik's cube (half a voxel: 1.9 mm) seen by one camera, its scan scattered 2 mm
    and thinned to a 2.5 mm spacing, as a far camera path leaves it: at its true pose half a
    voxel finds a scan point for fewer than ``min_fitness`` of its points, 1.5 spacings for
    as many as on the dense scan (a fitness that measured the scan, not the pose)."""
    from workers.pipeline.pose.candidates import FitContext
    from workers.pipeline.pose.crop import crop_scene

    mesh = shared_data / "ycb" / "rubiks_cube" / "textured.obj"
    model = prepare_model(mesh, tmp_path / "cube")
    true = upright(20.0, (0.0, 0.0, 0.0))
    true[2, 3] -= transform_points(true, model.points)[:, 2].min()
    scan, _ = partial_view(mesh, true, 3, camera_dirs=[np.array([1.0, 0.2, 1.0])])
    inputs = check_inputs(transform_points(true, model.points)[::10], None, None, UP)
    rng = np.random.default_rng(5)

    def fitness(voxel_m: float, inlier_spacings: float) -> tuple[float, float]:
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(scan.points))
        cloud.normals = o3d.utility.Vector3dVector(scan.normals)
        thin = cloud.voxel_down_sample(voxel_m)
        points = np.asarray(thin.points) + rng.normal(0.0, 0.002, (len(thin.points), 3))
        scene = SceneCloud.create(points, np.asarray(thin.normals))
        options = replace(POSE_PRESETS["default"], inlier_spacings=inlier_spacings)
        region = crop_scene(model, scene, inputs, options)
        refiner = Refiner.create(FitContext(model, region, (), options, inputs.up))
        return refiner.evaluate(true)[0], region.spacing_m

    dense, dense_spacing = fitness(0.001, 1.5)
    sparse, sparse_spacing = fitness(0.004, 1.5)
    voxels_only, _ = fitness(0.004, 0.0)
    assert dense_spacing < 0.0015 and 0.002 < sparse_spacing < 0.003
    assert voxels_only < POSE_PRESETS["default"].min_fitness < 0.9 * dense <= sparse
