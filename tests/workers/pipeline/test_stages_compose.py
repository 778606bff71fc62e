"""Every stage's output folder is the next stage's input: synth → reconstruct → compare →
model/pose through the command lines, as a capture-station author would run them."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from app.formats.cameras import load_cameras_file

ROOT = Path(__file__).resolve().parents[3]


def stage(*argv: str | Path, stdout: Path | None = None) -> None:
    """Run ``python -m workers.pipeline <argv>``; fail with its stderr when it fails."""
    out = stdout.open("w") if stdout is not None else subprocess.DEVNULL
    try:
        run = subprocess.run(
            [sys.executable, "-m", "workers.pipeline", *map(str, argv)],
            cwd=ROOT,
            stdout=out,
            stderr=subprocess.PIPE,
            text=True,
            timeout=300,
            check=False,
        )
    finally:
        if stdout is not None:
            out.close()  # type: ignore[union-attr]
    assert run.returncode == 0, f"{argv[0]} failed:\n{run.stderr[-3000:]}"


def rotation_deg(a: np.ndarray, b: np.ndarray) -> float:
    r = a[:3, :3].T @ b[:3, :3]
    return float(np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1))))


@pytest.mark.slow
def test_reconstruct_compare_and_pose_compose_through_the_command_lines(tmp_path: Path) -> None:
    """A 16-view scene where a wedge is added: the reconstruct folders are compare's input
    (cameras.json in the one format), compare finds the added wedge, and pose places it."""
    scene = tmp_path / "scene"
    stage("synth", "--scenario", "added", "--preset", "tiny", "--views", 16, "--poses",
          "--out", scene)  # fmt: skip
    truth = json.loads((scene / "ground_truth.json").read_text())["changes"]
    assert [(c["type"], c["object"]) for c in truth] == [("added", "wedge")]
    env_from_wedge = np.asarray(truth[0]["pose"])

    for capture in ("before", "after"):
        stage("reconstruct", scene / capture / "images", "--cameras",
              scene / capture / "cameras.json", "--reference", scene / "reference.json",
              "--out", tmp_path / capture, "--quiet")  # fmt: skip
        given = load_cameras_file(scene / capture / "cameras.json")
        written = load_cameras_file(tmp_path / capture / "cameras.json")
        assert set(written.poses) == set(given.poses) and written.intrinsics_per_image
        for name, pose in given.poses.items():  # known poses come back as given
            np.testing.assert_allclose(written.poses[name], pose, atol=1e-9)

    stage("compare", tmp_path / "before", tmp_path / "after",
          "--classes", scene / "after" / "classes.txt",
          "--before-labels", scene / "before" / "labels",
          "--after-labels", scene / "after" / "labels",
          "--out", tmp_path / "comparison.json", "--quiet")  # fmt: skip
    changes = json.loads((tmp_path / "comparison.json").read_text())["changes"]
    identified = [c for c in changes if c["object"] is not None]
    assert [(c["type"], c["object"]) for c in identified] == [("added", "wedge")]
    centroid = np.asarray(identified[0]["cluster"]["centroid"])
    # The wedge is about 0.4 m across: its cluster's centre lies over its true position.
    assert np.linalg.norm(centroid[:2] - env_from_wedge[:2, 3]) < 0.05

    stage("model", scene / "objects" / "wedge.ply", "--out", tmp_path / "wedge",
          "--units", "m", "--name", "wedge")  # fmt: skip
    stage("pose", "--model", tmp_path / "wedge", "--scene", tmp_path / "after" / "cloud.ply",
          "--center=" + ",".join(f"{v:.6f}" for v in centroid),
          stdout=tmp_path / "pose.json")  # fmt: skip
    posed = json.loads((tmp_path / "pose.json").read_text())
    env_from_object = np.asarray(posed["env_from_object"])
    assert posed["pose_quality"]["verified"] is True
    # A verified pose of a 0.4 m object from a 16-view capture: well inside 5 cm and 5°.
    assert np.linalg.norm(env_from_object[:3, 3] - env_from_wedge[:3, 3]) < 0.05
    assert rotation_deg(env_from_object, env_from_wedge) < 5.0
