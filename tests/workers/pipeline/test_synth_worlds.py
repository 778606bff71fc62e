"""The wider test world of the scene generator: all 18 YCB models, room layouts and their
supports, camera rings, real-camera effects, distractors, and the original presets kept
byte for byte."""

from __future__ import annotations

import hashlib
import json
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from app.formats.cameras import load_cameras_file
from workers.pipeline.errors import InputError
from workers.pipeline.geometry import invert_rigid, make_rigid, transform_points
from workers.pipeline.synth import (
    DISTRACTORS,
    PATH_PRESETS,
    PRESETS,
    REAL_CAMERA,
    ROOM_PRESETS,
    YCB_OBJECTS,
    CameraOptions,
    EffectsOptions,
    Placement,
    Scenario,
    SynthOptions,
    build_scenario,
    builtin_models,
    generate,
    load_model,
    load_true_surfaces,
    render_capture,
    view_effects,
    ycb_models,
)
from workers.pipeline.synth.cameras import intrinsics_matrix, look_at
from workers.pipeline.synth.cli import cli
from workers.pipeline.synth.markers import marker_corners_m, marker_sheet
from workers.pipeline.synth.options import RoomOptions
from workers.pipeline.synth.render import Renderer, distort_normalised
from workers.pipeline.synth.render import _pixel_rays as pixel_rays
from workers.pipeline.synth.scene import resting_faces

TINY = PRESETS["tiny"]
SMALL = CameraOptions(width=160, height=120, focal_px=130.0)


def _digest(root: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(root.rglob("*")):
        if p.is_file():
            h.update(str(p.relative_to(root)).encode())
            h.update(p.read_bytes())
    return h.hexdigest()


# sha256 over (relative path, bytes) of every file the generator wrote, measured by running
# e7676c5 (before the wider worlds) with the locked dependencies. The float paths the
# libraries pick differ by CPU, so the bytes do too: one set per machine kind it was run on.
BEFORE = (
    {  # the first CI machines
        "tiny_moved_3": "d580c60f0a8ea1e44425f81fc7dbb38a4b94a6b6932ce56c8b6d94aa53e3ddae",
        "tiny_table_swapped_2": "fa71b05d5f6d721f04b60212f86f429081ddb3ee76638008f41a3a30de13c336",
        "bench_small_multiple_1": (
            "50ac403115701aae617e5411f50395651f0fccf49e7a981ab7cf073b743eacbb"
        ),
    },
    {  # AMD EPYC with AVX-512 (e7676c5 run there in a worktree, 2026-11-24)
        "tiny_moved_3": "3aacaf71b141e49013ce6d61919bb08bdfa46b88d95c4fca9cbc8dc4a39178a0",
        "tiny_table_swapped_2": "2b8c2328be43c12f3cc9e3a92c7776c835e7594ea0ea1a7f8115fd1a9a7da116",
        "bench_small_multiple_1": (
            "64cb6a8404ec9a35cf0ca2d2d0fb7791e1ab5c1841aa4bfdf74245cc49c08c91"
        ),
    },
    {  # Intel Xeon (e7676c5 run there in a worktree, 2026-11-25)
        "tiny_moved_3": "97050eff3494d2a652de3929bff8085cab5220a878550c216f88d076960cd6f5",
        "tiny_table_swapped_2": "4fb6009b3f54690a9c3e06e4caa2b8bf1cc55bbef2d447c4b5d66d7c805893c9",
        "bench_small_multiple_1": (
            "bcf41ab7661f5c9abb6bd16b6c683d555ff7a5219ac9e5512b3201c20d45eea5"
        ),
    },
)


def test_original_presets_write_the_same_bytes(tmp_path: Path, shared_data: Path) -> None:
    """Scenes of the original options are written exactly as before: images, labels,
    cameras.json, ground_truth.json and models (so the bench scenes do not change). All
    three digests must be those e7676c5 wrote on one machine kind of ``BEFORE``; on a new
    kind, run e7676c5 there (``git worktree``) and add its set."""
    generate(tmp_path / "a", "moved", 3, TINY)
    with_table = replace(TINY, room=replace(TINY.room, table=True))
    generate(tmp_path / "b", "swapped", 2, with_table)
    names = ["power_drill", "large_clamp", "mustard_bottle", "master_chef_can", "hammer"]
    bench = PRESETS["bench"]
    small = replace(bench, camera=SMALL, path=replace(bench.path, n_views=2))
    generate(tmp_path / "c", "multiple", 1, small, ycb_models(shared_data / "ycb", names))
    got = {
        "tiny_moved_3": _digest(tmp_path / "a"),
        "tiny_table_swapped_2": _digest(tmp_path / "b"),
        "bench_small_multiple_1": _digest(tmp_path / "c"),
    }
    assert got in BEFORE


def test_every_ycb_model_loads_stands_up_and_renders(shared_data: Path) -> None:
    """All 18 models load with their texture, stand z up (flat ones low, tall ones taller
    than wide) and show textured pixels in a view from 0.6 m."""
    on_disk = sorted(p.name for p in (shared_data / "ycb").iterdir() if p.is_dir())
    assert sorted(YCB_OBJECTS) == on_disk and len(on_disk) == 18
    models = ycb_models(shared_data / "ycb", YCB_OBJECTS)
    camera = CameraOptions(width=96, height=72, focal_px=110.0)
    k = intrinsics_matrix(camera)
    look = PRESETS["tiny"].look
    markers = marker_sheet(RoomOptions())
    for model in models:
        assert model.uv_texture is not None, model.name
        size = model.mesh.vertices.max(0) - model.mesh.vertices.min(0)
        if model.name in ("adjustable_wrench", "large_clamp", "extra_large_clamp", "hammer"):
            assert size[2] < 0.05, (model.name, size)
        if model.name in ("pitcher_base", "mustard_bottle", "bleach_cleanser", "windex_bottle"):
            assert size[2] > max(size[0], size[1]), (model.name, size)
        placement = Placement("p", model, make_rigid(np.eye(3), -model.mesh.vertices.min(0)))
        renderer = Renderer((), (placement,), markers, camera, look, k)
        eye = np.asarray([0.45, 0.3, 0.35])
        target = np.asarray([0.0, 0.0, size[2] / 2])
        view = renderer.render(look_at(eye, target), np.random.default_rng(0))
        pixels = view.image[view.instance == 0].astype(float)
        assert len(pixels) > 40, model.name
        assert float(pixels.std(axis=0).mean()) > 3.0, model.name


def _check_rests(scenario: Scenario, capture: str) -> set[str]:
    """Every object of ``capture`` rests on its support: lowest point at the support's
    height (nothing below it, nothing floating more than 1 mm), inside a raised support's
    top, and floor objects clear of the raised supports; returns the supports used."""
    by_name = {s.name: s for s in scenario.supports}
    used = set()
    for p in scenario.capture(capture):
        support = by_name[p.support]
        points = transform_points(p.env_from_object, p.model.mesh.vertices)
        assert points[:, 2].min() == pytest.approx(support.z_m, abs=1e-3)
        assert points[:, 2].min() >= support.z_m - 1e-9
        used.add(p.support)
        for other in scenario.supports:
            if other.name == "floor":
                continue
            inside = np.all(
                np.abs(points[:, :2] - other.centre_m) <= np.asarray(other.size_m) / 2, axis=1
            )
            if other.name == p.support:
                assert inside.all(), (p.model.name, other.name)
            else:
                below_top = points[:, 2] < other.z_m
                assert not np.any(inside & below_top), (p.model.name, other.name)
    return used


@pytest.mark.parametrize("room", sorted(ROOM_PRESETS))
def test_layouts_stand_objects_on_their_supports(room: str) -> None:
    """Each room preset renders; its objects rest on the floor, table or shelf top."""
    path = "wide_high" if (ROOM_PRESETS[room].table or ROOM_PRESETS[room].shelf) else "ring"
    options = replace(
        TINY, room=ROOM_PRESETS[room], path=replace(PATH_PRESETS[path], n_views=1), camera=SMALL
    )
    used: set[str] = set()
    for seed in range(4):
        scenario = build_scenario("multiple", builtin_models(), seed, options)
        used |= _check_rests(scenario, "before") | _check_rests(scenario, "after")
    raised = {s.name for s in scenario.supports} - {"floor"}
    assert used == {"floor"} | raised
    walls = {s.name for s in scenario.room if s.name.startswith("wall")}
    assert len(walls) == {"closed": 4, "one_wall": 1, "two_walls": 2}[options.room.layout]
    (_, view) = next(iter(render_capture(scenario, "after", options)))
    assert (view.instance >= 0).sum() > 20
    assert float(view.image.std()) > 10.0


def test_ground_truth_lists_the_supports(tmp_path: Path) -> None:
    options = replace(
        TINY,
        room=ROOM_PRESETS["two_walls_table"],
        path=replace(PATH_PRESETS["wide_high"], n_views=2),
        camera=SMALL,
    )
    generate(tmp_path, "added", 0, options)
    gt = json.loads((tmp_path / "ground_truth.json").read_text())
    supports = {s["name"]: s for s in gt["supports"]}
    assert set(supports) == {"floor", "table"}
    assert supports["table"]["z_m"] == pytest.approx(0.5)
    assert gt["room"]["layout"] == "two_walls"
    # the room is rebuilt from the file: two walls, the table
    meshes = load_true_surfaces(tmp_path, "after")
    assert {"floor", "wall_0", "wall_2", "table"} <= set(meshes)
    assert "wall_1" not in meshes


def test_camera_rings_alternate_radius_and_height() -> None:
    options = replace(TINY, path=replace(PATH_PRESETS["low_high"], n_views=8))
    scenario = build_scenario("no_change", builtin_models(), 0, options)
    eyes = np.asarray(
        [v.env_from_cam[:3, 3] for _, v in render_capture(scenario, "before", options)]
    )
    (r0, h0), (r1, h1) = options.path.rings_m
    radius = np.linalg.norm(eyes[:, :2], axis=1)
    assert np.allclose(eyes[0::2, 2], h0, atol=0.051) and np.allclose(eyes[1::2, 2], h1, atol=0.051)
    assert np.allclose(radius[0::2], r0, atol=0.101) and np.allclose(radius[1::2], r1, atol=0.101)


def test_lens_model_matches_opencv_and_the_rays_invert_it() -> None:
    """The renderer's distortion is OpenCV's (projectPoints agrees to 1e-6 px) and each
    pixel's ray distorts back onto that pixel (1e-6 px)."""
    k = intrinsics_matrix(TINY.camera)
    dist = (REAL_CAMERA.k1, REAL_CAMERA.k2, REAL_CAMERA.p1, REAL_CAMERA.p2, 0.0)
    rays = pixel_rays(k, TINY.camera.width, TINY.camera.height, dist).astype(np.float64)
    cv_px, _ = cv2.projectPoints(rays.reshape(-1, 3), np.zeros(3), np.zeros(3), k, np.asarray(dist))
    u, v = np.meshgrid(np.arange(TINY.camera.width), np.arange(TINY.camera.height))
    grid = np.stack([u, v], axis=-1).reshape(-1, 2)
    # float32 rays: 1e-7 relative, well under 1e-3 px at 260 px focal length
    assert float(np.abs(cv_px.reshape(-1, 2) - grid).max()) < 1e-3
    xd, yd = distort_normalised(rays[..., 0], rays[..., 1], dist)
    ours = np.stack([xd * k[0, 0] + k[0, 2], yd * k[1, 1] + k[1, 2]], axis=-1).reshape(-1, 2)
    assert float(np.abs(ours - cv_px.reshape(-1, 2)).max()) < 1e-6
    # the lens really bends the image: the corners move by several pixels
    pinhole = pixel_rays(k, TINY.camera.width, TINY.camera.height)
    shift = np.linalg.norm((rays - pinhole)[0, 0, :2]) * k[0, 0]
    assert shift > 5.0


@pytest.mark.parametrize("model", ["OPENCV", "SIMPLE_RADIAL"])
def test_declared_lens_puts_the_markers_where_they_appear(tmp_path: Path, model: str) -> None:
    """In distorted 800×600 images, ArUco finds the marker corners where cameras.json's
    declared model (OpenCV's projectPoints with its params) puts them: mean < 0.5 px and no
    bias, as for the pinhole images (test_synth); the same corners through the pinhole part
    alone are off by several pixels."""
    effects = replace(REAL_CAMERA, distortion=model, motion_blur_px=0.0, exposure_jitter=0.0)
    options = replace(
        TINY,
        camera=CameraOptions(),
        path=replace(TINY.path, n_views=3),
        effects=effects,
        write_poses=True,
    )
    scenario = generate(tmp_path, "no_change", 0, options)
    declared = load_cameras_file(tmp_path / "before" / "cameras.json")
    camera = declared.intrinsics
    assert camera is not None and camera.model == model
    fx, fy, cx, cy = camera.pinhole
    k = np.asarray([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    dist = np.asarray(camera.distortion)
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    detector = cv2.aruco.ArucoDetector(dictionary, params)
    offsets, pinhole_offsets = [], []
    for name, pose in declared.poses.items():
        image = cv2.imread(str(tmp_path / "before" / "images" / name), cv2.IMREAD_GRAYSCALE)
        corners, ids, _ = detector.detectMarkers(image)
        assert ids is not None
        cam_from_env = invert_rigid(np.asarray(pose))
        for marker_id, found in zip(ids.ravel(), corners, strict=True):
            env_from_marker = scenario.markers.env_from_marker[int(marker_id)]
            corners_env = transform_points(env_from_marker, marker_corners_m(0.15))
            corners_cam = transform_points(cam_from_env, corners_env)
            px, _ = cv2.projectPoints(corners_cam, np.zeros(3), np.zeros(3), k, dist)
            offsets.append(found.reshape(4, 2) - px.reshape(4, 2))
            plain, _ = cv2.projectPoints(corners_cam, np.zeros(3), np.zeros(3), k, None)
            pinhole_offsets.append(found.reshape(4, 2) - plain.reshape(4, 2))
    offset_px = np.concatenate(offsets)
    error_px = np.linalg.norm(offset_px, axis=1)
    assert len(error_px) >= 12
    assert float(np.linalg.norm(offset_px.mean(axis=0))) < 0.15
    assert float(np.mean(error_px)) < 0.5
    assert float(np.mean(np.linalg.norm(np.concatenate(pinhole_offsets), axis=1))) > 3.0


def test_self_calibration_writes_no_intrinsics(tmp_path: Path) -> None:
    effects = EffectsOptions(distortion="OPENCV", k1=-0.1, declare_intrinsics=False)
    options = replace(
        TINY, camera=SMALL, path=replace(TINY.path, n_views=2), effects=effects, write_poses=False
    )
    generate(tmp_path, "added", 0, options)
    assert not (tmp_path / "before" / "cameras.json").exists()
    gt = json.loads((tmp_path / "ground_truth.json").read_text())
    assert gt["camera"]["model"] == "OPENCV" and gt["camera"]["params"][4] == -0.1
    with pytest.raises(InputError, match="declared intrinsics"):
        generate(tmp_path / "posed", "added", 0, replace(options, write_poses=True))
    assert not (tmp_path / "posed").exists()
    with pytest.raises(InputError, match="distortion model"):
        bad = replace(options, effects=EffectsOptions(distortion="FISHEYE"))
        generate(tmp_path / "bad", "added", 0, bad)


def _first_view(scenario: Scenario, capture: str, options: SynthOptions) -> np.ndarray:
    _, view = next(iter(render_capture(scenario, capture, options)))
    return view.image.astype(np.float64)


def test_effects_are_deterministic_and_do_what_they_say() -> None:
    plain = replace(TINY, camera=SMALL, path=replace(TINY.path, n_views=2))
    scenario = build_scenario("no_change", builtin_models(), 5, plain)
    gain_only = EffectsOptions(capture_gain=(1.0, 1.2))
    warm = EffectsOptions(capture_white_balance=((1, 1, 1), (1.1, 1.0, 0.9)))
    base_after = _first_view(scenario, "after", plain)
    # the same view (no_change: same placements; the path follows the seed) with a gain
    brighter = _first_view(scenario, "after", replace(plain, effects=gain_only))
    lit = (base_after > 20) & (base_after < 200)
    assert np.median(brighter[lit] / base_after[lit]) == pytest.approx(1.2, abs=0.02)
    assert np.array_equal(
        _first_view(scenario, "before", replace(plain, effects=gain_only)),
        _first_view(scenario, "before", plain),
    )
    warmer = _first_view(scenario, "after", replace(plain, effects=warm))
    ratio = warmer.reshape(-1, 3).sum(0) / base_after.reshape(-1, 3).sum(0)
    assert ratio[0] > 1.05 and ratio[2] < 0.95
    # blur: less high-frequency energy; deterministic per seed, different across views
    blur = replace(plain, effects=EffectsOptions(motion_blur_px=4.0))
    blurred = _first_view(scenario, "after", blur)
    lap = [
        float(np.abs(cv2.Laplacian(img.mean(axis=2), cv2.CV_64F)).mean())
        for img in (base_after, blurred)
    ]
    assert lap[1] < 0.8 * lap[0]
    assert np.array_equal(blurred, _first_view(scenario, "after", blur))
    # exposure jitter: per-view log gains with the stated spread, the same for the same seed
    jitter = replace(plain, effects=EffectsOptions(exposure_jitter=0.1))
    gains = [view_effects(jitter, 5, "before", i) for i in range(300)]
    log_gain = np.log([g.gain_rgb[0] for g in gains if g is not None])
    assert float(np.std(log_gain)) == pytest.approx(0.1, rel=0.2)
    again = view_effects(jitter, 5, "before", 7)
    assert again is not None and np.array_equal(again.gain_rgb, gains[7].gain_rgb)  # type: ignore[union-attr]
    assert view_effects(plain, 5, "before", 0) is None


def test_real_camera_preset_writes_distorted_jpegs(tmp_path: Path) -> None:
    options = replace(
        PRESETS["real_camera"], camera=SMALL, path=replace(PRESETS["real_camera"].path, n_views=2)
    )
    generate(tmp_path, "added", 3, options)
    images = sorted((tmp_path / "after" / "images").iterdir())
    assert [p.suffix for p in images] == [".jpg", ".jpg"]
    camera = load_cameras_file(tmp_path / "after" / "cameras.json").intrinsics
    assert camera is not None and camera.model == "OPENCV"
    assert camera.distortion[:4] == (REAL_CAMERA.k1, REAL_CAMERA.k2, REAL_CAMERA.p1, REAL_CAMERA.p2)
    # the after capture is brighter than the before (gain 1.15) on average
    mean = {
        c: np.mean([cv2.imread(str(p)).mean() for p in (tmp_path / c / "images").iterdir()])
        for c in ("before", "after")
    }
    assert mean["after"] > mean["before"]


def test_distractors_are_unidentified_changes(tmp_path: Path) -> None:
    options = replace(
        TINY, camera=SMALL, path=replace(TINY.path, n_views=3), distractors=DISTRACTORS
    )
    scenario = generate(tmp_path, "removed", 1, options)
    gt = json.loads((tmp_path / "ground_truth.json").read_text())
    unidentified = [c for c in gt["changes"] if c.get("unidentified")]
    assert sorted(c["distractor"] for c in unidentified) == sorted(DISTRACTORS)
    assert all(c["type"] == "added" and c["object"] is None for c in unidentified)
    assert [c["type"] for c in gt["changes"] if not c.get("unidentified")] == ["removed"]
    classes = (tmp_path / "after" / "classes.txt").read_text().split()
    assert not set(DISTRACTORS) & set(classes) and not set(DISTRACTORS) & set(gt["objects"])
    items = {i["instance_id"]: i for i in gt["after"]}
    for c in unidentified:
        assert items[c["instance_id"]]["class_id"] is None and items[c["instance_id"]]["distractor"]
    # the detector never boxes a distractor, though it is seen
    seen = False
    for _index, (name, view) in enumerate(render_capture(scenario, "after", options)):
        d_index = [i for i, p in enumerate(scenario.after) if p.model.name in DISTRACTORS]
        seen |= bool(np.isin(view.instance, d_index).any())
        label = (tmp_path / "after" / "labels" / (Path(name).stem + ".txt")).read_text()
        assert all(int(line.split()[0]) < len(classes) for line in label.splitlines())
    assert seen
    column = load_true_surfaces(tmp_path, "after")[unidentified[0]["instance_id"]]
    assert float(np.asarray(column.vertices)[:, 2].max()) > 0.2
    with pytest.raises(InputError, match="distractor"):
        build_scenario("added", builtin_models(), 0, replace(TINY, distractors=("ghost",)))


def test_target_picks_what_is_swapped_out() -> None:
    models = builtin_models()
    for target in ("l_bracket", "crate", "stepped_block"):
        scenario = build_scenario("swapped", models, 2, replace(TINY, target=target))
        (change,) = scenario.changes
        assert change["replaced_object"] == target and change["object"] == "wedge"
    with pytest.raises(InputError, match="target"):
        build_scenario("removed", models, 0, replace(TINY, target="wedge"))


def test_model_loads_ycb_symmetry(shared_data: Path) -> None:
    """The round YCB objects keep their declared symmetry through :func:`ycb_models`."""
    can, bowl = ycb_models(shared_data / "ycb", ["master_chef_can", "bowl"])
    assert can.symmetry is not None and bowl.symmetry is not None
    assert load_model(shared_data / "ycb" / "padlock" / "textured.obj").symmetry is None


def test_cli_builds_a_wider_world(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    args = ["--scenario", "removed", "--out", str(tmp_path), "--preset", "tiny", "--views", "1"]
    world = ["--room", "one_wall", "--path", "low_high", "--real-camera"]
    lying = ["--lying", "crate,wedge"]
    assert cli([*args, *world, "--distractors", "column", "--target", "crate", *lying]) == 0
    gt = json.loads((tmp_path / "ground_truth.json").read_text())
    assert gt["room"]["layout"] == "one_wall" and gt["effects"]["distortion"] == "OPENCV"
    assert [c.get("distractor") for c in gt["changes"]] == [None, "column"]
    assert gt["changes"][0]["object"] == "crate"
    crate = next(p for p in gt["before"] if p["object"] == "crate")
    assert np.asarray(crate["env_from_object"])[2, 2] < 0.98  # not on its base
    assert cli([*args, "--distractors", "ghost"]) == 1
    assert "unknown distractor" in capsys.readouterr().err


def test_resting_faces_of_a_box_are_its_five_sides_but_the_base() -> None:
    corners = np.array([[x, y, z] for x in (-0.1, 0.1) for y in (-0.05, 0.05) for z in (0, 0.05)])
    normals = sorted(tuple(np.round(n, 6)) for n in resting_faces(corners))
    assert normals == sorted([(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1)])
    # a long low wedge: its steep short face does not hold the foot of its centre
    section = [(0.0, 0.0), (1.0, 0.0), (0.9, 0.1)]
    wedge = np.array([[x, y, z] for x, z in section for y in (0.0, 0.2)])
    normals = resting_faces(wedge)
    assert any(n[2] > 0.9 for n in normals)  # the long slope
    assert not any(n[0] > 0.5 for n in normals)


def test_lying_objects_rest_on_another_face_apart() -> None:
    models = builtin_models()
    names = tuple(m.name for m in models)
    options = replace(TINY, lying=names)
    for seed in range(3):
        scenario = build_scenario("multiple", models, seed, options)
        for capture in ("before", "after"):
            _check_rests(scenario, capture)
            placed = scenario.capture(capture)
            for p in placed:
                # object z no longer up: set down on a side or upside down
                assert p.env_from_object[2, 2] < np.cos(np.radians(10.0)), (seed, p.model.name)
            for i, a in enumerate(placed):
                for b in placed[i + 1 :]:
                    (xa, ra), (xb, rb) = a.footprint_env(), b.footprint_env()
                    if a.support == b.support:
                        assert np.linalg.norm(xa - xb) >= ra + rb, (a.model.name, b.model.name)
    upright = build_scenario("multiple", models, 0, TINY)
    assert all(p.env_from_object[2, 2] == pytest.approx(1.0) for p in upright.before)
    with pytest.raises(InputError, match="lying"):
        build_scenario("moved", models, 0, replace(TINY, lying=("ghost",)))
