"""The scene generator: determinism, label and pose oracles, markers, scenarios, YCB models."""

from __future__ import annotations

import hashlib
import json
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest

from workers.pipeline.errors import InputError
from workers.pipeline.geometry import invert_rigid, make_rigid, pose_error, transform_points
from workers.pipeline.model.symmetry_group import spec_from_json, symmetric_pose_error
from workers.pipeline.synth import (
    CAPTURES,
    PRESETS,
    SCENARIOS,
    CameraOptions,
    DetectionOptions,
    Scenario,
    build_scenario,
    builtin_models,
    detect,
    generate,
    load_model,
    load_true_surfaces,
    render_capture,
    true_surfaces,
    visible_boxes,
    yolo_lines,
)
from workers.pipeline.synth.cameras import camera_path, intrinsics_matrix
from workers.pipeline.synth.cli import cli
from workers.pipeline.synth.markers import marker_corners_m, rot_z

TINY = PRESETS["tiny"]


def _digest(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


@pytest.fixture(scope="module")
def moved(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Scenario]:
    out = tmp_path_factory.mktemp("moved")
    return out, generate(out, "moved", seed=3, options=TINY)


def test_same_seed_gives_identical_files(tmp_path: Path, moved: tuple[Path, Scenario]) -> None:
    generate(tmp_path / "again", "moved", seed=3, options=TINY)
    first, again = _digest(moved[0]), _digest(tmp_path / "again")
    assert first == again
    assert len([k for k in first if k.endswith(".png")]) == 2 * TINY.path.n_views
    other = build_scenario("moved", builtin_models(), 4, TINY)
    _, view = next(iter(render_capture(other, "before", TINY)))
    assert not np.array_equal(view.image, cv2.imread(str(moved[0] / "before/images/view_000.png")))


def test_labels_are_the_extent_of_visible_pixels(moved: tuple[Path, Scenario]) -> None:
    out, scenario = moved
    classes = (out / "before" / "classes.txt").read_text().splitlines()
    w, h = TINY.camera.width, TINY.camera.height
    n_boxes = 0
    for capture in ("before", "after"):
        placements = scenario.capture(capture)
        for name, view in render_capture(scenario, capture, TINY):
            stored = cv2.imread(str(out / capture / "images" / name))[:, :, ::-1]
            assert np.array_equal(stored, view.image)
            expected = {
                (classes.index(placements[i].model.name), x0, y0, x1, y1)
                for i, (x0, y0, x1, y1, _) in visible_boxes(
                    view.instance, TINY.detection.min_visible_px
                ).items()
            }
            got = set()
            label = out / capture / "labels" / (Path(name).stem + ".txt")
            for line in label.read_text().splitlines():
                cls, cx, cy, bw, bh, conf = line.split()
                box = (float(cx) - float(bw) / 2, float(cy) - float(bh) / 2)
                x0, y0 = round(box[0] * w), round(box[1] * h)
                got.add((int(cls), x0, y0, x0 + round(float(bw) * w), y0 + round(float(bh) * h)))
                assert 0 < float(conf) <= 1
            assert got == expected
            n_boxes += len(got)
    assert n_boxes >= 2 * TINY.path.n_views


def test_ground_truth_round_trips_through_the_files(moved: tuple[Path, Scenario]) -> None:
    out, scenario = moved
    gt = json.loads((out / "ground_truth.json").read_text())
    for capture in ("before", "after"):
        placements = scenario.capture(capture)
        assert [o["instance_id"] for o in gt[capture]] == [p.instance_id for p in placements]
        for item, p in zip(gt[capture], placements, strict=True):
            assert item["object"] == p.model.name
            np.testing.assert_allclose(item["env_from_object"], p.env_from_object, atol=1e-12)
        cameras = json.loads((out / capture / "cameras.json").read_text())
        assert cameras["intrinsics"]["model"] == "PINHOLE"
        assert cameras["intrinsics"]["params"][:2] == [TINY.camera.focal_px] * 2
        path = camera_path(TINY.path, np.random.default_rng([3, 2, CAPTURES.index(capture)]))
        assert len(cameras["poses"]) == len(path) == TINY.path.n_views
        for name, env_from_cam in zip(sorted(cameras["poses"]), path, strict=True):
            np.testing.assert_allclose(cameras["poses"][name], env_from_cam, atol=1e-12)
            assert gt["camera_poses"][capture][name] == cameras["poses"][name]
            assert (out / capture / "images" / name).is_file()
    reference = json.loads((out / "reference.json").read_text())
    assert reference == gt["reference"] == scenario.markers.reference()
    assert reference["markers"]["dictionary"] == "DICT_4X4_50"
    for model in scenario.models:
        mesh = o3d.io.read_triangle_mesh(str(out / "objects" / f"{model.name}.ply"))
        assert mesh.has_vertex_colors()
        np.testing.assert_allclose(np.asarray(mesh.vertices), model.mesh.vertices, atol=1e-6)


def test_depth_lies_on_the_true_surfaces(moved: tuple[Path, Scenario]) -> None:
    """Back-projected depth is within 1 mm of the true meshes read back from the files."""
    out, scenario = moved
    meshes = load_true_surfaces(out, "after")
    assert set(meshes) >= {"floor"} | {p.instance_id for p in scenario.after}
    in_memory = true_surfaces(scenario, "after")
    for key, mesh in in_memory.items():
        np.testing.assert_allclose(
            np.asarray(meshes[key].vertices), np.asarray(mesh.vertices), atol=1e-6
        )
    scene = o3d.t.geometry.RaycastingScene()
    for mesh in meshes.values():
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    k_inv = np.linalg.inv(intrinsics_matrix(TINY.camera))
    _, view = next(iter(render_capture(scenario, "after", TINY)))
    v, u = np.nonzero(np.isfinite(view.depth_m))
    rays = np.column_stack([u, v, np.ones_like(u)]) @ k_inv.T
    points_cam = rays / np.linalg.norm(rays, axis=1, keepdims=True) * view.depth_m[v, u, None]
    points_env = transform_points(view.env_from_cam, points_cam)
    dist = scene.compute_distance(o3d.core.Tensor(points_env.astype(np.float32))).numpy()
    assert float(np.max(dist)) < 1e-3


def test_markers_are_detected_where_they_project() -> None:
    """At 800×600 cv2.aruco (sub-pixel corners) finds the printed markers in every view, and
    their corners land where the known marker poses project.

    Tolerance: no bias (mean error vector < 0.1 px, which a half-pixel convention slip would
    break), mean < 0.5 px, 90 % < 1 px; the worst corners, on markers seen at grazing angles
    with 3–4 px per bit, reach about 1.5 px, hence 2 px for the maximum.
    """
    options = replace(TINY, camera=CameraOptions(), path=replace(TINY.path, n_views=4))
    scenario = build_scenario("no_change", builtin_models(), 0, options)
    k = intrinsics_matrix(options.camera)
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    detector = cv2.aruco.ArucoDetector(dictionary, params)
    offsets, counts = [], []
    size = scenario.markers.size_m
    for _, view in render_capture(scenario, "before", options):
        corners, ids, _ = detector.detectMarkers(cv2.cvtColor(view.image, cv2.COLOR_RGB2GRAY))
        assert ids is not None
        counts.append(len(ids))
        cam_from_env = invert_rigid(view.env_from_cam)
        for marker_id, found in zip(ids.ravel(), corners, strict=True):
            env_from_marker = scenario.markers.env_from_marker[int(marker_id)]
            corners_env = transform_points(env_from_marker, marker_corners_m(size))
            projected = transform_points(cam_from_env, corners_env) @ k.T
            offsets.append(found.reshape(4, 2) - projected[:, :2] / projected[:, 2:])
    assert min(counts) >= 1 and np.mean(counts) >= 2.5
    offset_px = np.concatenate(offsets)
    error_px = np.linalg.norm(offset_px, axis=1)
    assert float(np.linalg.norm(offset_px.mean(axis=0))) < 0.1
    assert float(np.mean(error_px)) < 0.5
    assert float(np.quantile(error_px, 0.9)) < 1.0
    assert float(np.max(error_px)) < 2.0


def _rests_without_overlap(scenario: Scenario, capture: str) -> None:
    placements = scenario.capture(capture)
    for p in placements:
        lowest = transform_points(p.env_from_object, p.model.mesh.vertices)[:, 2].min()
        support_z = 0.0 if p.support == "floor" else PRESETS["tiny"].room.table_size_m[2]
        assert lowest == pytest.approx(support_z, abs=1e-9)
    for i, a in enumerate(placements):
        for b in placements[i + 1 :]:
            (a_xy, a_r), (b_xy, b_r) = a.footprint_env(), b.footprint_env()
            if a.support == b.support:
                assert np.linalg.norm(a_xy - b_xy) > a_r + b_r


def _vacated_places_stay_free(scenario: Scenario) -> None:
    """No new or moved object overlaps the footprint of a removed or moved one (swaps aside)."""
    changed_types = ("removed", "moved")
    before = {p.instance_id: p for p in scenario.before}
    after = {p.instance_id: p for p in scenario.after}
    changed = [c for c in scenario.changes if c["type"] in ("added", "moved")]
    vacated = [before[c["instance_id"]] for c in scenario.changes if c["type"] in changed_types]
    for change in changed:
        new = after[change["instance_id"]]
        for old in vacated:
            # a moved object may overlap its own old place (move_min_m rules that)
            if old.support != new.support or old.instance_id == new.instance_id:
                continue
            (n_xy, n_r), (o_xy, o_r) = new.footprint_env(), old.footprint_env()
            assert np.linalg.norm(n_xy - o_xy) > n_r + o_r, (change, old.instance_id)


@pytest.mark.parametrize("seed", range(12))
def test_multiple_keeps_each_change_in_its_own_place(seed: int) -> None:
    """The added object does not land where the removed one stood (it would read as a swap)."""
    _vacated_places_stay_free(build_scenario("multiple", builtin_models(), seed, TINY))


@pytest.mark.parametrize("name", SCENARIOS)
def test_each_scenario_has_its_change(name: str) -> None:
    scenario = build_scenario(name, builtin_models(), 7, TINY)
    _rests_without_overlap(scenario, "before")
    _rests_without_overlap(scenario, "after")
    before = {p.instance_id: p for p in scenario.before}
    after = {p.instance_id: p for p in scenario.after}
    kinds = sorted(c["type"] for c in scenario.changes)
    expected = {
        "added": ["added"],
        "removed": ["removed"],
        "moved": ["moved"],
        "swapped": ["swapped"],
        "symmetric_moved": ["moved"],
        "multiple": ["added", "moved", "removed"],
        "no_change": [],
    }[name]
    assert kinds == expected
    for change in scenario.changes:
        iid = change["instance_id"]
        if change["type"] == "added":
            assert iid in after and iid not in before
        if change["type"] == "removed":
            assert iid in before and iid not in after
            np.testing.assert_allclose(change["previous_pose"], before[iid].env_from_object)
        if change["type"] == "moved":
            shift = after[iid].footprint_env()[0] - before[iid].footprint_env()[0]
            assert np.linalg.norm(shift) >= TINY.move_min_m
            np.testing.assert_allclose(change["pose"], after[iid].env_from_object)
            assert (before[iid].model.symmetry is not None) == (name == "symmetric_moved")
        if change["type"] == "swapped":
            old = next(p for p in scenario.before if p.model.name == change["replaced_object"])
            assert change["object"] != change["replaced_object"]
            assert old.instance_id not in after
            near = after[iid].footprint_env()[0] - old.footprint_env()[0]
            assert np.linalg.norm(near) < 0.35
    _vacated_places_stay_free(scenario)
    if name == "no_change":
        assert [p.env_from_object.tolist() for p in scenario.before] == [
            p.env_from_object.tolist() for p in scenario.after
        ]


def test_builtin_shapes_need_no_shared_data(tmp_path: Path) -> None:
    models = builtin_models()
    assert len([m for m in models if m.symmetry is None]) >= 3
    assert any(m.symmetry is not None for m in models)
    for m in models:
        extent = m.mesh.vertices.max(axis=0) - m.mesh.vertices.min(axis=0)
        assert 0.15 <= extent.max() <= 0.40
        assert m.mesh.signed_volume() > 0
    out = tmp_path / "cli"
    options = ["--preset", "tiny", "--views", "2", "--seed", "1", "--no-poses"]
    assert cli(["--scenario", "added", "--out", str(out), *options]) == 0
    assert len(list((out / "after" / "images").glob("*.png"))) == 2
    assert "poses" not in json.loads((out / "after" / "cameras.json").read_text())
    assert len(json.loads((out / "ground_truth.json").read_text())["camera_poses"]["after"]) == 2
    options = ["--preset", "tiny", "--views", "1", "--seed", "1"]
    assert cli(["--scenario", "added", "--out", str(out), *options]) == 0
    assert [p.name for p in (out / "after" / "labels").iterdir()] == ["view_000.txt"]
    assert sorted(p.stem for p in (out / "objects").glob("*.ply")) == sorted(m.name for m in models)


def test_scenarios_refuse_what_they_cannot_build() -> None:
    no_symmetric = [m for m in builtin_models() if m.symmetry is None]
    with pytest.raises(InputError):
        build_scenario("symmetric_moved", no_symmetric, 0, TINY)
    with pytest.raises(InputError):
        build_scenario("teleported", builtin_models(), 0, TINY)


def test_ycb_models_render_with_their_texture(shared_data: Path) -> None:
    names = ["power_drill", "mustard_bottle", "tomato_soup_can"]
    models = [load_model(shared_data / "ycb" / n / "textured.obj", n) for n in names]
    assert models[2].symmetry is not None and models[0].symmetry is None
    options = replace(TINY, path=replace(TINY.path, n_views=2))
    scenario = build_scenario("added", models, 0, options)
    drill = [i for i, p in enumerate(scenario.after) if p.model.name == "power_drill"]
    assert drill
    pixels = []
    for _, view in render_capture(scenario, "after", options):
        pixels.append(view.image[view.instance == drill[0]].astype(float))
    colours = np.concatenate(pixels)
    assert len(colours) > 100
    assert float(colours.std(axis=0).mean()) > 15.0


def test_ycb_texture_is_not_upside_down(shared_data: Path) -> None:
    """The cracker box is printed all over; its texture atlas is 43 % black padding, so
    sampling the atlas upside down turns about 40 % of the surface black."""
    box = load_model(shared_data / "ycb" / "cracker_box" / "textured.obj")
    colours = box.colours_at_vertices()
    assert box.name == "cracker_box"
    assert float(np.mean(colours.max(axis=1) < 0.1)) < 0.03


def test_texture_is_view_consistent(moved: tuple[Path, Scenario]) -> None:
    """A floor point has the same colour in two views (solid texture, Lambertian shading):
    pixel pairs that see one point differ far less than random pixel pairs do."""
    _, scenario = moved
    views = [view for _, view in render_capture(scenario, "before", TINY)][:2]
    k = intrinsics_matrix(TINY.camera)
    k_inv = np.linalg.inv(k)
    first, second = views
    v, u = np.nonzero(np.isfinite(first.depth_m) & (first.instance < 0))
    rays = np.column_stack([u, v, np.ones_like(u)]) @ k_inv.T
    points_cam = rays / np.linalg.norm(rays, axis=1, keepdims=True) * first.depth_m[v, u, None]
    points_env = transform_points(first.env_from_cam, points_cam)
    in_second = transform_points(invert_rigid(second.env_from_cam), points_env)
    pix = in_second @ k.T
    uv = np.rint(pix[:, :2] / pix[:, 2:]).astype(int)
    h, w = first.depth_m.shape
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    u2, v2 = uv[inside, 0], uv[inside, 1]
    seen = np.abs(second.depth_m[v2, u2] - np.linalg.norm(in_second[inside], axis=1)) < 0.005
    assert seen.sum() > 2000
    a = first.image[v[inside][seen], u[inside][seen]].astype(float)
    b = second.image[v2[seen], u2[seen]].astype(float)
    same = float(np.median(np.abs(a - b)))
    shuffled = float(np.median(np.abs(a - np.random.default_rng(0).permutation(b))))
    assert same < 6.0 and shuffled > 3 * same


def test_symmetric_pose_error_forgives_turns_about_the_axis() -> None:
    drum = next(m for m in builtin_models() if m.symmetry is not None)
    true = make_rigid(np.eye(3), [0.3, -0.2, 0.0])
    turn = np.eye(4)
    turn[:3, :3] = rot_z(np.radians(37.0))
    spec = spec_from_json(drum.symmetry)
    assert symmetric_pose_error(true @ turn, true, spec) == pytest.approx((0, 0), abs=1e-5)
    t_err, r_err = pose_error(true @ turn, true)
    assert r_err == pytest.approx(37.0, abs=1e-6) and t_err == pytest.approx(0.0, abs=1e-12)
    tilt = make_rigid(np.asarray([[1, 0, 0], [0, 0, -1], [0, 1, 0]]), [0, 0, 0])
    assert symmetric_pose_error(true @ tilt, true, spec)[1] == pytest.approx(90.0)


def test_detection_corruption_options() -> None:
    """Misses drop boxes, false positives add boxes of no instance, jitter stays in the image."""
    instance = np.full((60, 80), -1, np.int32)
    instance[10:30, 5:25] = 0
    instance[40:55, 50:78] = 1
    rng = np.random.default_rng(0)
    clean = detect(instance, [2, 0], 3, DetectionOptions(min_visible_px=10), rng)
    assert sorted((d.class_id, d.box_px) for d in clean) == [
        (0, (50, 40, 78, 55)),
        (2, (5, 10, 25, 30)),
    ]
    few = detect(instance, [2, 0], 3, DetectionOptions(min_visible_px=401), rng)
    assert [d.instance for d in few] == [1]  # 20×20 = 400 px is too few, 28×15 = 420 is not
    assert detect(instance, [2, 0], 3, DetectionOptions(miss_rate=1.0), rng) == []
    noisy = detect(
        instance, [2, 0], 3, DetectionOptions(false_positive_rate=1.0, box_jitter_px=3.0), rng
    )
    assert [d.instance for d in noisy].count(-1) == 1 and len(noisy) == 3
    for d in noisy:
        x0, y0, x1, y1 = d.box_px
        assert 0 <= x0 < x1 <= 80 and 0 <= y0 < y1 <= 60
    line = yolo_lines(clean[:1], 80, 60, confidence=False).split()
    assert len(line) == 5 and float(line[3]) == pytest.approx(20 / 80)


def test_bad_inputs_raise_input_errors(tmp_path: Path, moved: tuple[Path, Scenario]) -> None:
    models = builtin_models()
    with pytest.raises(InputError):
        build_scenario("added", models[:1], 0, TINY)
    with pytest.raises(InputError):
        moved[1].capture("during")
    with pytest.raises(InputError):
        load_model(tmp_path / "missing.ply")
    with pytest.raises(InputError):
        load_true_surfaces(tmp_path, "before")
    # a model file written by the generator loads back as a vertex-coloured model
    crate = load_model(moved[0] / "objects" / "crate.ply")
    assert crate.name == "crate" and crate.vertex_colours is not None
