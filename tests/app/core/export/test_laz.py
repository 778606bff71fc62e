"""PLY → LAZ against laspy reading it back: every point within 0.1 mm, colours scaled from
8 to 16 bits exactly, the header's note, chunked reading, and the cached conversion that
concurrent requests share."""

from __future__ import annotations

import os
import threading
from pathlib import Path

import laspy
import numpy as np
import open3d as o3d
import pytest

from app.core.errors import Conflict
from app.core.export import laz
from app.core.export.laz import SCALE_M, SYSTEM_IDENTIFIER, ensure_laz, laz_key, write_laz
from app.core.export.ply import read_model
from app.core.storage import LocalStorage

GENERATOR = "twindelta test"


def write_cloud(path: Path, n: int, colored: bool = True, seed: int = 0) -> None:
    """A cloud of ``n`` points in a 12 m room offset from the origin (coloured: 8-bit)."""
    rng = np.random.default_rng(seed)
    cloud = o3d.geometry.PointCloud(
        o3d.utility.Vector3dVector(rng.uniform(-4, 8, (n, 3)) + np.array([100.0, -50.0, 0.3]))
    )
    if colored:
        cloud.colors = o3d.utility.Vector3dVector(rng.integers(0, 256, (n, 3)) / 255.0)
    path.parent.mkdir(parents=True, exist_ok=True)
    assert o3d.io.write_point_cloud(str(path), cloud)


def test_laz_reads_back_as_the_ply_within_a_tenth_of_a_millimetre(tmp_path: Path) -> None:
    write_cloud(tmp_path / "cloud.ply", 25_000)
    # chunks of 4096 points: the conversion never holds the cloud whole
    assert write_laz(tmp_path / "cloud.ply", tmp_path / "cloud.laz", GENERATOR, 4096) == 25_000
    ply = read_model(tmp_path / "cloud.ply")
    las = laspy.read(tmp_path / "cloud.laz")
    assert las.header.point_count == 25_000 and las.header.point_format.id == 2
    assert np.abs(las.xyz - ply.positions).max() <= SCALE_M / 2 + 1e-9
    rgb16 = np.stack([las.red, las.green, las.blue], axis=1).astype(np.int64)
    rgb8 = np.round(ply.colors * 255).astype(np.int64)  # type: ignore[operator]
    np.testing.assert_array_equal(rgb16, rgb8 * 257)  # 255 → 65535
    np.testing.assert_array_equal(las.header.scales, [SCALE_M] * 3)
    np.testing.assert_array_equal(las.header.offsets, np.floor(ply.positions.min(axis=0)))
    assert las.header.system_identifier == SYSTEM_IDENTIFIER
    assert las.header.generating_software == GENERATOR
    assert tmp_path.joinpath("cloud.laz").read_bytes()[:4] == b"LASF"


def test_a_cloud_without_colours_gets_a_point_format_without_them(tmp_path: Path) -> None:
    write_cloud(tmp_path / "cloud.ply", 100, colored=False)
    write_laz(tmp_path / "cloud.ply", tmp_path / "cloud.laz", GENERATOR)
    las = laspy.read(tmp_path / "cloud.laz")
    assert las.header.point_format.id == 0 and las.header.point_count == 100


def test_the_laz_is_converted_once_and_again_only_when_the_ply_is_newer(
    tmp_path: Path,
) -> None:
    storage = LocalStorage(tmp_path)
    ply_key = "snapshots/s/reconstruction/cloud.ply"
    write_cloud(storage.path(ply_key), 1000)
    key = ensure_laz(storage, ply_key, GENERATOR)
    assert key == laz_key(ply_key) == "snapshots/s/reconstruction/cloud.laz"
    first = storage.path(key).stat()
    assert ensure_laz(storage, ply_key, GENERATOR) == key
    assert storage.path(key).stat().st_ino == first.st_ino  # kept, not rewritten
    write_cloud(storage.path(ply_key), 700, seed=1)
    later = first.st_mtime_ns + 1_000_000_000
    os.utime(storage.path(ply_key), ns=(later, later))
    ensure_laz(storage, ply_key, GENERATOR)
    assert laspy.read(storage.path(key)).header.point_count == 700


def test_concurrent_conversions_convert_once_and_leave_one_whole_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    calls: list[Path] = []

    def counted(ply: Path, out: Path, generator: str, chunk: int) -> int:
        calls.append(out)
        return write_laz(ply, out, generator, chunk)

    monkeypatch.setattr(laz, "write_laz", counted)
    storage = LocalStorage(tmp_path)
    ply_key = "snapshots/s/reconstruction/cloud.ply"
    write_cloud(storage.path(ply_key), 60_000)
    start = threading.Barrier(4)
    errors: list[BaseException] = []

    def convert() -> None:
        start.wait()
        try:
            ensure_laz(storage, ply_key, GENERATOR, chunk=8192)
        except BaseException as exc:  # reported below
            errors.append(exc)

    threads = [threading.Thread(target=convert) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == [] and len(calls) == 1
    folder = storage.path(ply_key).parent
    assert sorted(p.name for p in folder.iterdir()) == ["cloud.laz", "cloud.ply"]
    assert laspy.read(folder / "cloud.laz").header.point_count == 60_000


def test_an_unreadable_ply_is_a_conflict_and_leaves_nothing(tmp_path: Path) -> None:
    storage = LocalStorage(tmp_path)
    ply_key = "snapshots/s/reconstruction/cloud.ply"
    storage.write_bytes(ply_key, b"ply\nformat ascii 1.0\nelement vertex 2\nend_header\n")
    with pytest.raises(Conflict, match="no vertex element") as caught:
        ensure_laz(storage, ply_key, GENERATOR)
    assert caught.value.code == "PointCloudUnreadable"
    assert [p.name for p in storage.path(ply_key).parent.iterdir()] == ["cloud.ply"]
