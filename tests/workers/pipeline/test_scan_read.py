"""Scan readers against files written by independent writers (pye57, laspy, Open3D): every
point back with its colour, E57 scans moved by their own poses, chunking that changes
nothing, and the streaming voxel average equal to the one-shot one."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pye57
import pytest

from tests.workers.pipeline.scan_scene import cloud, write_e57, write_las, write_ply
from workers.pipeline.geometry import make_rigid, rotation_from_rotvec, transform_points
from workers.pipeline.reconstruct.fusion import voxel_average
from workers.pipeline.scan import ScanReadError, iter_scan, kabsch
from workers.pipeline.scan.voxels import VoxelGrid


def read_all(path: Path, fmt: str, chunk: int = 97) -> tuple[np.ndarray, np.ndarray | None]:
    chunks = list(iter_scan(path, fmt, chunk))  # type: ignore[arg-type]
    points = np.concatenate([c.points for c in chunks])
    colors = None if chunks[0].colors is None else np.concatenate([c.colors for c in chunks])  # type: ignore[misc]
    return points, colors


def test_e57_scans_come_back_in_the_common_frame_with_their_colours(tmp_path: Path) -> None:
    (p1, c1), (p2, c2) = cloud(300, seed=1), cloud(120, seed=2)
    pose1 = make_rigid(rotation_from_rotvec([0.3, -0.2, 1.1]), [1.0, -2.0, 0.5])
    pose2 = make_rigid(rotation_from_rotvec([0.0, 0.0, -2.0]), [4.0, 0.0, 0.0])
    path = tmp_path / "two.e57"
    write_e57(path, [(p1, c1, pose1), (p2, c2, pose2)])
    points, colors = read_all(path, "e57")
    expected = np.concatenate([transform_points(pose1, p1), transform_points(pose2, p2)])
    # pye57 stores coordinates as doubles: the poses (quaternions) are the only rounding
    np.testing.assert_allclose(points, expected, atol=1e-6)
    assert colors is not None and np.array_equal(colors, np.concatenate([c1, c2]))


def test_e57_invalid_points_are_dropped_and_intensity_is_grey(tmp_path: Path) -> None:
    points, _ = cloud(50)
    invalid = np.zeros(50, np.int8)
    invalid[::5] = 1
    path = tmp_path / "intensity.e57"
    with pye57.E57(str(path), mode="w") as e57:
        e57.write_scan_raw(
            {
                "cartesianX": points[:, 0].copy(),
                "cartesianY": points[:, 1].copy(),
                "cartesianZ": points[:, 2].copy(),
                "intensity": np.linspace(0.0, 1.0, 50),
                "cartesianInvalidState": invalid,
            }
        )
    got, colors = read_all(path, "e57", chunk=7)
    np.testing.assert_allclose(got, points[invalid == 0], atol=1e-9)
    assert colors is not None and np.all(colors[:, 0] == colors[:, 2])
    assert colors[0, 0] < colors[-1, 0]  # brighter with intensity


@pytest.mark.parametrize("suffix", ["las", "laz"])
def test_las_and_laz_points_and_16_bit_colours(tmp_path: Path, suffix: str) -> None:
    points, colors = cloud(1000, seed=3)
    path = tmp_path / f"cloud.{suffix}"
    write_las(path, points, colors, scale_m=1e-4)
    got, got_colors = read_all(path, suffix, chunk=300)
    np.testing.assert_allclose(got, points, atol=0.5e-4 + 1e-9)  # the LAS scale
    assert got_colors is not None and np.array_equal(got_colors, colors)


def test_las_without_colours_gives_grey_from_intensity(tmp_path: Path) -> None:
    points, _ = cloud(10)
    path = tmp_path / "grey.las"
    write_las(path, points, None)
    got, colors = read_all(path, "las")
    assert len(got) == 10 and colors is not None and not colors.any()  # intensity 0: black


@pytest.mark.parametrize("ascii", [False, True])
def test_ply_binary_and_ascii(tmp_path: Path, ascii: bool) -> None:
    points, colors = cloud(400, seed=4)
    path = tmp_path / "cloud.ply"
    write_ply(path, points, colors, ascii=ascii)
    got, got_colors = read_all(path, "ply", chunk=150)
    np.testing.assert_allclose(got, points, atol=1e-6)
    assert got_colors is not None and np.array_equal(got_colors, colors)


def test_big_endian_ply_with_float_colours(tmp_path: Path) -> None:
    points = np.asarray([[1.0, 2.0, 3.0], [-4.0, 5.5, 6.25]])
    header = (
        b"ply\nformat binary_big_endian 1.0\nelement vertex 2\nproperty double x\n"
        b"property double y\nproperty double z\nproperty float red\nproperty float green\n"
        b"property float blue\nend_header\n"
    )
    rows = np.zeros(2, dtype=[("p", ">f8", 3), ("c", ">f4", 3)])
    rows["p"], rows["c"] = points, [[1.0, 0.5, 0.0], [0.0, 0.0, 1.0]]
    path = tmp_path / "be.ply"
    path.write_bytes(header + rows.tobytes())
    got, colors = read_all(path, "ply")
    np.testing.assert_array_equal(got, points)
    assert colors is not None and colors.tolist() == [[255, 128, 0], [0, 0, 255]]


def test_a_damaged_file_is_a_scan_read_error(tmp_path: Path) -> None:
    points, colors = cloud(3000)
    path = tmp_path / "cut.laz"
    write_las(path, points, colors)
    path.write_bytes(path.read_bytes()[:-400])
    with pytest.raises(ScanReadError, match="LAZ scan: cannot read its points"):
        read_all(path, "laz")


def test_streaming_voxel_average_equals_the_one_shot_average() -> None:
    points, colors = cloud(20_000, seed=5)
    points *= 0.05  # dense enough that voxels hold several points
    grid = VoxelGrid(0.004, merge_every=500)  # merges many times
    for start in range(0, len(points), 3_000):
        grid.add(points[start : start + 3_000], colors[start : start + 3_000])
    got, got_colors = grid.result()
    want, want_colors = voxel_average(points, 0.004, colors)
    order_got = np.lexsort(np.floor(got / 0.004).T)
    order_want = np.lexsort(np.floor(want / 0.004).T)
    np.testing.assert_allclose(got[order_got], want[order_want], atol=1e-12)
    assert got_colors is not None
    assert np.abs(got_colors[order_got].astype(int) - want_colors[order_want]).max() <= 1
    assert grid.n_in == 20_000 and len(got) < 20_000


def test_kabsch_recovers_a_rigid_transform() -> None:
    rng = np.random.default_rng(0)
    src = rng.normal(size=(12, 3))
    dst_from_src = make_rigid(rotation_from_rotvec(rng.normal(size=3)), rng.normal(size=3))
    np.testing.assert_allclose(
        kabsch(src, transform_points(dst_from_src, src)), dst_from_src, atol=1e-12
    )
