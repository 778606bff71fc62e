"""The scan stage: a given transform places the cloud exactly; the marker sheet found in a
synthetic coloured scan (a generated room, the sheet printed on its floor, moved by a known
random rigid transform) gives the frame within 1 mm / 0.2°; without the print it fails
NoUsableFrame; the cloud has the photo pipeline's density; an all-invalid scan is EmptyScan."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d
import pytest

from app.formats.scan import ScanFrame
from tests.workers.pipeline.scan_scene import cloud, synthetic_scan, write_e57, write_ply
from workers.pipeline.geometry import (
    invert_rigid,
    make_rigid,
    pose_error,
    rotation_from_rotvec,
    transform_points,
)
from workers.pipeline.reconstruct.markers import parse_reference
from workers.pipeline.reconstruct.options import ReconstructOptions
from workers.pipeline.scan import (
    EmptyScan,
    NoUsableFrame,
    ScanInput,
    ScanOptions,
    ScanTooDense,
    find_sheet,
    scan_to_cloud,
)
from workers.pipeline.scan import markers as scan_markers

VOXEL_M = ReconstructOptions().voxel_size_m  # the density of a photo snapshot's cloud


def frame(env_from_scan: np.ndarray, units: str = "m") -> ScanFrame:
    rows = tuple(tuple(float(v) for v in row) for row in env_from_scan)
    return ScanFrame("transform", rows, units)  # type: ignore[arg-type]


def test_a_transform_frame_places_the_cloud_and_sets_its_density(tmp_path: Path) -> None:
    points, colors = cloud(20_000, seed=1)
    points *= 0.2  # 40 cm cube: voxels of 2.5 mm hold several points
    env_from_scan = make_rigid(rotation_from_rotvec([0.1, 0.7, -0.3]), [2.0, -1.0, 0.5])
    path = tmp_path / "scan.ply"
    write_ply(path, points * 1000.0, colors)  # stored in millimetres
    result = scan_to_cloud(
        ScanInput(path, "ply", frame(env_from_scan, "mm"), 20_000), tmp_path / "out", VOXEL_M
    )
    out = o3d.io.read_point_cloud(str(result.cloud_path))
    got = np.asarray(out.points)
    assert out.has_colors() and result.cloud_path.read_bytes().startswith(b"ply\nformat binary")
    # every output point is a voxel mean of input points moved into the env frame
    moved = transform_points(env_from_scan, points)
    tree = o3d.geometry.KDTreeFlann(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(moved)))
    nearest = [np.sqrt(tree.search_knn_vector_3d(p, 1)[2][0]) for p in got[:500]]
    assert max(nearest) < np.sqrt(3) * VOXEL_M
    assert len(got) == len(np.unique(np.floor(got / VOXEL_M), axis=0))  # one point per voxel
    q = result.quality
    assert q["points_in"] == 20_000 and q["points"] == len(got) < 20_000
    assert (q["frame_method"], q["units"], q["voxel_size_m"]) == ("transform", "mm", VOXEL_M)
    assert q["marker_residual_m"] is None and q["alignment_residual_m"] == 0.0
    np.testing.assert_allclose(q["env_from_scan"], env_from_scan)
    assert result.cameras_path.read_text() == '{"images": {}}'


@pytest.mark.slow
def test_the_marker_sheet_in_a_coloured_scan_gives_the_frame(tmp_path: Path) -> None:
    """An E57 in millimetres whose scan pose is the scanner's: the frame found within 1 mm
    at the sheet and 0.2°. Single corners are off by up to ~2 mm (1.5 mm raster pixels of
    2 mm point spacing); the fit over the 32 corners of 8 markers averages that down
    (measured 0.1–0.2 mm and 0.002–0.011° over seeds 0, 1, 3)."""
    scan = synthetic_scan(seed=3)
    common_from_scanner = make_rigid(rotation_from_rotvec([0.0, 0.0, 0.8]), [0.4, -0.2, 1.1])
    points_scanner = transform_points(invert_rigid(common_from_scanner), scan.points_scan)
    mm = np.diag([1000.0, 1000.0, 1000.0, 1.0])
    path = tmp_path / "room.e57"
    write_e57(
        path, [(points_scanner * 1000.0, scan.colors, mm @ common_from_scanner @ np.linalg.inv(mm))]
    )
    calls: list[tuple[str, float]] = []
    result = scan_to_cloud(
        ScanInput(path, "e57", ScanFrame("markers", None, "mm"), len(scan.points_scan)),
        tmp_path / "out",
        VOXEL_M,
        parse_reference(scan.sheet.reference()),
        progress=lambda stage, fraction: calls.append((stage, fraction)),
    )
    marker_steps = [f for stage, f in calls if stage == "markers"]
    assert calls[0][0] == "read" and calls[-1] == ("write", 1.0)
    assert marker_steps == sorted(marker_steps) and len(set(marker_steps)) > 3  # per plane
    q = result.quality
    # the error where the sheet is: the environment's origin, and the rotation
    dt, dr = pose_error(invert_rigid(np.asarray(q["env_from_scan"])), scan.scan_from_env)
    print(
        f"marker frame: {dt * 1000:.2f} mm, {dr:.4f}°; "
        f"residual {q['marker_residual_m'] * 1000:.2f} mm"
    )
    assert dt < 0.001 and dr < 0.2
    assert q["markers_used"] == sorted(scan.sheet.env_from_marker) and q["marker_refined"]
    assert q["frame_method"] == "markers" and 0 < q["marker_residual_m"] < 0.003
    assert q["alignment_residual_m"] == q["marker_residual_m"]
    floor = np.asarray(o3d.io.read_point_cloud(str(result.cloud_path)).points)
    near_origin = floor[np.linalg.norm(floor[:, :2], axis=1) < 1.0]
    assert abs(np.median(near_origin[:, 2])) < 0.001  # the floor is z = 0 in the env frame


def test_without_the_printed_sheet_the_frame_is_not_usable(tmp_path: Path) -> None:
    scan = synthetic_scan(seed=4, floor_spacing_m=0.006, printed=False)
    path = tmp_path / "plain.ply"
    write_ply(path, scan.points_scan, scan.colors)
    with pytest.raises(NoUsableFrame, match=r"none of the environment's DICT_4X4_50 markers"):
        scan_to_cloud(
            ScanInput(path, "ply", ScanFrame("markers", None, "m")),
            tmp_path / "out",
            VOXEL_M,
            parse_reference(scan.sheet.reference()),
        )


def test_markers_in_a_scan_without_colours_are_not_usable(tmp_path: Path) -> None:
    points, _ = cloud(100)
    path = tmp_path / "plain.ply"
    write_ply(path, points, None)
    sheet = {"markers": {"size": 0.15, "poses": {"0": np.eye(4).tolist()}}}
    with pytest.raises(NoUsableFrame, match="neither colours nor intensity"):
        scan_to_cloud(
            ScanInput(path, "ply", ScanFrame("markers", None, "m")),
            tmp_path / "out",
            VOXEL_M,
            parse_reference(sheet),
        )


def test_a_scan_without_a_finite_point_is_empty(tmp_path: Path) -> None:
    """Points that are not finite are dropped; none left is EmptyScan (the header promised
    20; invalid-flagged E57 points are dropped the same way, test_scan_read)."""
    header = (
        b"ply\nformat binary_little_endian 1.0\nelement vertex 20\nproperty float x\n"
        b"property float y\nproperty float z\nend_header\n"
    )
    path = tmp_path / "nan.ply"
    path.write_bytes(header + np.full((20, 3), np.nan, "<f4").tobytes())
    with pytest.raises(EmptyScan, match="no valid points"):
        scan_to_cloud(ScanInput(path, "ply", frame(np.eye(4)), 20), tmp_path / "out", VOXEL_M)


def test_the_command_line_runs_the_stage(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from workers.pipeline.__main__ import main

    points, colors = cloud(300)
    write_ply(tmp_path / "scan.ply", points, colors)
    (tmp_path / "scan.ply").rename(tmp_path / "scan.bin")  # recognised by content, not name
    transform = json.dumps({"transform": np.eye(4).tolist(), "units": "cm"})
    args = ["scan", str(tmp_path / "scan.bin"), "--out", str(tmp_path / "out"), "--quiet"]
    assert main([*args, "--frame", transform]) == 0
    quality = json.loads(capsys.readouterr().out)
    assert quality["points_in"] == 300 and (tmp_path / "out" / "cloud.ply").is_file()
    assert main([*args, "--frame", '{"markers": true}']) == 1  # no reference: no sheet
    assert json.loads(capsys.readouterr().out)["error"] == "NoUsableFrame"


def test_large_planes_are_rasterised_in_tiles(monkeypatch: pytest.MonkeyPatch) -> None:
    """Tiles of 400 px (0.6 m, overlapping by two marker sides) instead of one raster: every
    marker is still found once, and the frame is as good (a plant's floor would otherwise be
    one image of 10⁸ pixels)."""
    scan = synthetic_scan(seed=5)
    reference = parse_reference(scan.sheet.reference())
    centres = transform_points(
        scan.scan_from_env, np.asarray([p[:3, 3] for p in reference.poses.values()])
    )
    near = np.zeros(len(scan.points_scan), bool)
    for centre in centres:
        near |= np.linalg.norm(scan.points_scan - centre, axis=1) < 0.25
    sides: list[int] = []
    raster = scan_markers._raster

    def recording(*args: Any) -> Any:
        img, origin = raster(*args)
        sides.append(max(img.shape))
        return img, origin

    monkeypatch.setattr(scan_markers, "_raster", recording)
    fit = find_sheet(
        scan.points_scan[near], scan.colors[near], reference, ScanOptions(raster_tile_px=400)
    )
    assert len(sides) > 4 and max(sides) <= 400 + 2  # never one image of the whole floor
    assert fit.used == tuple(sorted(reference.poses))
    dt, dr = pose_error(invert_rigid(fit.env_from_scan), scan.scan_from_env)
    assert dt < 0.001 and dr < 0.2


def test_a_scan_too_dense_for_the_memory_allowed_fails_naming_the_way_out(tmp_path: Path) -> None:
    points, colors = cloud(5000)
    path = tmp_path / "dense.ply"
    write_ply(path, points, colors)
    options = ScanOptions(max_voxels=1000, chunk_points=1000)
    with pytest.raises(ScanTooDense, match="coarser reconstruct voxel_size_m"):
        scan_to_cloud(
            ScanInput(path, "ply", frame(np.eye(4))), tmp_path / "out", VOXEL_M, None, options
        )
    result = scan_to_cloud(  # the same scan, 25 cm voxels: within the limit
        ScanInput(path, "ply", frame(np.eye(4))), tmp_path / "out", 0.25, None, options
    )
    assert result.quality["points"] <= 1000
