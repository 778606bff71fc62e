"""The command line: two capture folders on disk → the comparison JSON."""

from __future__ import annotations

import json
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
from workers.pipeline.compare.files import load_capture, load_labels
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
