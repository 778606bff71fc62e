"""The command line: two capture folders on disk → the comparison JSON."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from tests.workers.pipeline.compare_scene import (
    CLASSES,
    DIAMETERS,
    bin_,
    capture,
    crate,
    ring_cameras,
)
from workers.pipeline.__main__ import main
from workers.pipeline.compare import CaptureData
from workers.pipeline.compare.files import load_capture, load_labels, read_photo
from workers.pipeline.errors import InputError
from workers.pipeline.geometry import invert_rigid


def write_capture(folder: Path, cap: CaptureData) -> None:
    (folder / "labels").mkdir(parents=True)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cap.points_env))
    o3d.io.write_point_cloud(str(folder / "cloud.ply"), pcd)
    cam0 = cap.cameras[0]
    k = cam0.k
    doc = {
        "intrinsics": {
            "model": "PINHOLE",
            "width": cam0.width,
            "height": cam0.height,
            "params": [k[0, 0], k[1, 1], k[0, 2], k[1, 2]],
        },
        "poses": {f"{c.name}.png": invert_rigid(c.cam_from_env).tolist() for c in cap.cameras},
    }
    (folder / "cameras.json").write_text(json.dumps(doc))
    for name, rows in cap.detections.items():
        lines = [
            f"{int(r[0])} {r[1]:.6f} {r[2]:.6f} {r[3]:.6f} {r[4]:.6f} {r[5]:.3f}" for r in rows
        ]
        (folder / "labels" / f"{name}.txt").write_text("\n".join(lines) + "\n")
    (folder / "classes.txt").write_text("\n".join(CLASSES) + "\n")


def test_cli_compares_two_capture_folders(tmp_path: Path) -> None:
    cams = ring_cameras()
    base = [crate(-0.8, 0.5), bin_(0.7, -0.6)]
    write_capture(tmp_path / "before", capture(base, cams, 1))
    write_capture(tmp_path / "after", capture([*base, crate(0.6, 0.8)], cams, 2))
    loaded = load_capture(tmp_path / "after")
    assert len(loaded.cameras) == 8 and loaded.cameras[0].name == "img00.png"
    np.testing.assert_allclose(loaded.cameras[0].cam_from_env, cams[0].cam_from_env, atol=1e-12)
    assert loaded.detections["img00.png"].shape[1] == 6
    (tmp_path / "diameters.json").write_text(json.dumps(DIAMETERS))
    twin = [{"instance_id": "c1", "object": "crate", "pose": np.eye(4).tolist()}]
    (tmp_path / "twin.json").write_text(json.dumps({"objects": twin}))
    out = tmp_path / "result.json"
    argv = [
        "compare",
        str(tmp_path / "before"),
        str(tmp_path / "after"),
        "--quiet",
        "--diameters",
        str(tmp_path / "diameters.json"),
        "--twin",
        str(tmp_path / "twin.json"),
        "--options",
        '{"threshold": {"kind": "mean_std", "k": 1.5}}',
        "--out",
        str(out),
        "--clusters-dir",
        str(tmp_path / "clusters"),
    ]
    assert main(argv) == 0
    doc = json.loads(out.read_text())
    assert doc["options"]["threshold"] == {"kind": "mean_std", "k": 1.5}
    assert [(c["type"], c["object"]) for c in doc["changes"]] == [("added", "crate")]
    assert (tmp_path / "clusters" / "cluster_1_added.npy").is_file()


def test_cli_reports_bad_input(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["compare", str(tmp_path / "nope"), str(tmp_path / "nope2")]) == 2
    assert "classes.txt" in capsys.readouterr().err
    bad = tmp_path / "bad.txt"
    bad.write_text("0 0.5 0.5 0.1 0.1\n0 0.5 0.5 1.5 0.1\n")
    with pytest.raises(InputError, match=r"bad.txt line 2: w = 1.5 is outside 0..1"):
        load_labels(bad)


def test_a_capture_folder_brings_its_photos_read_undistorted_and_reduced(tmp_path: Path) -> None:
    """Photos in images/ beside labels/ come with the capture; read_photo reads one at a
    reduced size, undistorted by the camera's lens, and gives None for a photo it cannot
    use (unreadable, or not the camera's size)."""
    import cv2

    cams = ring_cameras()
    write_capture(tmp_path / "cap", capture([crate(0.0, 0.0)], cams, 1))
    (tmp_path / "cap" / "images").mkdir()
    cam = cams[0]
    img = np.zeros((cam.height, cam.width, 3), np.uint8)
    img[:, : cam.width // 2] = (255, 0, 0)  # blue on the left (BGR)
    img[cam.height // 2 - 20 : cam.height // 2 + 20, cam.width - 60 : cam.width - 20] = 255
    cv2.imwrite(str(tmp_path / "cap" / "images" / f"{cam.name}.png"), img)
    (tmp_path / "cap" / "images" / f"{cams[1].name}.png").write_bytes(b"not an image")
    loaded = load_capture(tmp_path / "cap")
    assert sorted(loaded.photos) == [f"{cams[0].name}.png", f"{cams[1].name}.png"]
    first, second = loaded.cameras[0], loaded.cameras[1]
    photo = read_photo(loaded.photos[first.name], first, 256)
    assert photo is not None and photo.dtype == np.float32
    assert max(photo.shape[:2]) >= 256 and max(photo.shape[:2]) < max(cam.width, cam.height)
    np.testing.assert_allclose(photo[5, 5], [0.0, 0.0, 1.0])  # RGB
    assert read_photo(loaded.photos[second.name], second, 256) is None
    small = replace(first, width=first.width // 2)
    assert read_photo(loaded.photos[first.name], small, 256) is None
    # a barrel lens moves the white patch near the edge inwards once undistorted
    barrel = replace(first, distortion=(-0.3, 0.0, 0.0, 0.0, 0.0))
    straight = read_photo(loaded.photos[first.name], barrel, 256)
    assert straight is not None
    cols = np.flatnonzero(photo[photo.shape[0] // 2, :, 1] > 0.5)
    cols_straight = np.flatnonzero(straight[straight.shape[0] // 2, :, 1] > 0.5)
    assert cols_straight.max() > cols.max()
