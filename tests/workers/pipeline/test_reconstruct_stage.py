"""The reconstruct stage end to end: SfM on real photos, known poses, markers, failures, CLI."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from app.formats.cameras import load_cameras_file
from tests.workers.pipeline.reconstruct_scene import write_scene
from workers.pipeline.errors import InputError
from workers.pipeline.geometry import pose_error
from workers.pipeline.reconstruct import options_from_preset, parse_cameras, reconstruct
from workers.pipeline.reconstruct.cli import cli
from workers.pipeline.reconstruct.common import list_images
from workers.pipeline.reconstruct.errors import NoReferenceFrame, TooFewImages
from workers.pipeline.reconstruct.fusion import read_ply, write_ply
from workers.pipeline.reconstruct.sfm import run_sfm

TUM_INTRINSICS = {
    "intrinsics": {
        "model": "PINHOLE",
        "width": 640,
        "height": 480,
        "params": [535.4, 539.2, 320.1, 247.6],
    }
}


@pytest.fixture(scope="module")
def plane_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("plane")
    write_scene(root, n_views=10)
    return root


@pytest.mark.slow
def test_all_17_tum_frames_register_with_given_intrinsics(
    shared_data: Path, tmp_path: Path
) -> None:
    images = shared_data / "tum_fr3_office"
    names = list_images(images)
    assert len(names) == 17
    model = run_sfm(
        images, tmp_path, names, options_from_preset("default"), parse_cameras(TUM_INTRINSICS)
    )
    assert sorted(v.name for v in model.views) == names
    assert model.mean_reprojection_error_px < 1.0
    assert len(model.points) > 1000
    # given intrinsics are held fixed (returned in OpenCV's pixel convention)
    np.testing.assert_allclose(model.views[0].intrinsics.params, [535.4, 539.2, 320.1, 247.6])


def test_known_poses_give_a_cloud_in_the_environment_frame(
    plane_scene: Path, tmp_path: Path
) -> None:
    """Poses from cameras.json define the frame: the floor (z = 0) comes back with median
    |z| < 1 mm and p95 < 5 mm; output cameras equal the given poses; marker check < 2 mm."""
    raw = json.loads((plane_scene / "cameras.json").read_text())
    ref = json.loads((plane_scene / "reference.json").read_text())
    options = options_from_preset(planar_prior=True)  # the default, named: the test reads it
    res = reconstruct(plane_scene / "images", tmp_path, options, parse_cameras(raw), ref)
    q = res.quality
    assert q["mode"] == "known_poses" and q["frame_source"] == "camera_poses"
    assert q["far_range"] is True
    assert q["images_registered"] == q["images_total"] == 10
    assert q["marker_residual_m"] < 0.002
    pts, cols = read_ply(res.cloud_path)
    assert len(pts) == q["points"] > 20000
    assert np.median(np.abs(pts[:, 2])) < 0.001
    assert np.percentile(np.abs(pts[:, 2]), 95) < 0.005
    assert np.abs(pts[:, :2]).max() < 0.6
    assert cols.std() > 10  # coloured
    assert res.cloud_path.read_bytes()[:200].count(b"binary_little_endian") == 1
    written = load_cameras_file(res.cameras_path)  # the one format: the next stage's input
    for name, pose in raw["poses"].items():
        np.testing.assert_allclose(written.poses[name], pose, atol=1e-12)
    assert set(q["timings_s"]) >= {"sparse", "stereo", "planar", "consistency", "fusion", "total"}
    # the planar prior finds the floor (z = 0 within 2 mm) and reports what it filled
    floor = q["planar"]["planes"][0]
    assert abs(abs(floor["normal"][2]) - 1.0) < 1e-3 and abs(floor["offset_m"]) < 0.002
    assert set(q["planar"]) == {"planes", "pixels_filled", "far_pixels_replaced"}
    assert q["planar"]["pixels_filled"] >= 0 and q["planar"]["far_pixels_replaced"] >= 0


def test_a_reference_cloud_lends_its_planes_and_an_empty_one_is_refused(
    plane_scene: Path, tmp_path: Path
) -> None:
    """The environment's reference cloud (its floor and a wall at x = 1.5 m, which the new
    photos do not show) adds the wall to the planar prior's planes (the floor it shares is
    not added twice) and the new cloud is refined against it. An empty reference cloud is
    refused before the dense stage, with no cloud written."""
    raw = json.loads((plane_scene / "cameras.json").read_text())
    ref = json.loads((plane_scene / "reference.json").read_text())
    rng = np.random.default_rng(0)
    floor = np.c_[rng.uniform(-0.6, 0.6, (20000, 2)), np.zeros(20000)]
    wall = np.c_[np.full(8000, 1.5), rng.uniform(-1, 1, 8000), rng.uniform(0, 1, 8000)]
    cloud = tmp_path / "reference.ply"
    write_ply(cloud, np.concatenate([floor, wall]), np.full((28000, 3), 128, np.uint8))
    options = options_from_preset(planar_prior=True)
    cams = parse_cameras(raw)
    res = reconstruct(plane_scene / "images", tmp_path / "a", options, cams, ref, cloud)
    planes = res.quality["planar"]["planes"]
    assert sum(abs(abs(p["normal"][2]) - 1.0) < 1e-3 for p in planes) == 1
    assert any(
        abs(abs(p["normal"][0]) - 1.0) < 1e-3 and abs(abs(p["offset_m"]) - 1.5) < 0.002
        for p in planes
    )
    assert res.quality["alignment_correction"] is not None
    empty = tmp_path / "empty.ply"
    empty.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 0\nend_header\n")
    with pytest.raises(InputError, match="empty or unreadable"):
        reconstruct(plane_scene / "images", tmp_path / "b", options, cams, ref, empty)
    assert not (tmp_path / "b" / "cloud.ply").exists()


def test_sfm_with_markers_recovers_cameras_in_metres(plane_scene: Path, tmp_path: Path) -> None:
    """SfM (intrinsics only) + marker alignment: camera centres within 5 mm of the truth
    (median < 3 mm), marker residual reported and < 2 mm, floor median |z| < 2 mm."""
    raw = json.loads((plane_scene / "cameras.json").read_text())
    ref = json.loads((plane_scene / "reference.json").read_text())
    cams = parse_cameras({"intrinsics": raw["intrinsics"]})
    res = reconstruct(plane_scene / "images", tmp_path, options_from_preset(), cams, ref)
    q = res.quality
    assert q["mode"] == "sfm" and q["frame_source"] == "markers"
    assert q["far_range"] is True
    assert q["images_registered"] == 10
    assert 0 < q["marker_residual_m"] < 0.002
    errs = [pose_error(v.env_from_cam, np.array(raw["poses"][v.name]))[0] for v in res.views]
    assert np.median(errs) < 0.003 and max(errs) < 0.006
    pts, _ = read_ply(res.cloud_path)
    assert np.median(np.abs(pts[:, 2])) < 0.002


def test_too_few_images(tmp_path: Path, plane_scene: Path) -> None:
    images = tmp_path / "images"
    images.mkdir()
    shutil.copy(plane_scene / "images" / "view_000.png", images)
    with pytest.raises(TooFewImages) as err:
        reconstruct(images, tmp_path / "work", options_from_preset())
    assert err.value.code == "TooFewImages"


def test_no_reference_frame_is_refused_before_any_work(plane_scene: Path, tmp_path: Path) -> None:
    raw = json.loads((plane_scene / "cameras.json").read_text())
    cams = parse_cameras({"intrinsics": raw["intrinsics"]})
    with pytest.raises(NoReferenceFrame) as err:
        reconstruct(plane_scene / "images", tmp_path, options_from_preset(), cams, None)
    assert err.value.code == "NoReferenceFrame"
    assert "markers" in err.value.detail and "cameras.json" in err.value.detail
    assert not (tmp_path / "sfm").exists()


def test_presets_and_overrides() -> None:
    assert options_from_preset("fast", voxel_size_m=0.003).voxel_size_m == 0.003
    with pytest.raises(InputError):
        options_from_preset("nope")
    with pytest.raises(InputError):
        options_from_preset("default", no_such_option=1)
    # values are checked against the option's type, naming the option
    opts = options_from_preset(voxel_size_m=1, planar_min_points=200.0, icp_max_distances_m=[1, 2])
    assert opts.voxel_size_m == 1.0 and isinstance(opts.voxel_size_m, float)
    assert opts.planar_min_points == 200 and isinstance(opts.planar_min_points, int)
    assert opts.icp_max_distances_m == (1.0, 2.0)
    assert options_from_preset().cuda_dense is False
    assert options_from_preset(cuda_dense=True).cuda_dense is True
    assert options_from_preset(sgbm_mode="3way").sgbm_mode == "3way"
    for bad in (
        {"cuda_dense": "yes"},
        {"sgbm_mode": "3wya"},  # a closed set: a typo is refused, not a KeyError mid-run
        {"sgbm_mode": 3},
        {"planar_min_points": 2.5},
        {"voxel_size_m": "1"},
        {"seed": True},
        {"icp_max_distances_m": ["a"]},
        {"preset": 3},
    ):
        with pytest.raises(InputError, match=next(iter(bad))):
            options_from_preset(**bad)


def test_cli_runs_and_reports_errors_as_json(
    plane_scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rc = cli(
        [
            str(plane_scene / "images"),
            "--out",
            str(tmp_path / "out"),
            "--cameras",
            str(plane_scene / "cameras.json"),
            "--preset",
            "fast",
            "--quiet",
        ]
    )
    assert rc == 0
    assert json.loads(capsys.readouterr().out)["points"] > 1000
    assert (tmp_path / "out" / "cloud.ply").exists()
    assert (tmp_path / "out" / "quality.json").exists()
    rc = cli([str(plane_scene / "images"), "--out", str(tmp_path / "out2"), "--quiet"])
    assert rc == 1
    assert json.loads(capsys.readouterr().out)["error"] == "NoReferenceFrame"
