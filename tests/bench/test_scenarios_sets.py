"""The scenario benchmark's world sets: distractor scoring and the per-set report (the
pipeline itself is replaced by a recorder; the real run is ``make bench``)."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from bench import scenarios_bench
from bench.scenarios_bench import DISTRACTOR_REACH_M, score_distractors
from bench.worlds import TEST, real_camera
from workers.pipeline.synth import PRESETS


def _found(obj: str | None, xy: tuple[float, float], cluster: int) -> dict[str, Any]:
    return {"type": "added", "object": obj, "cluster": {"id": cluster, "centroid": [*xy, 0.5]}}


def _truth(xy: tuple[float, float]) -> dict[str, Any]:
    pose = np.eye(4)
    pose[:2, 3] = xy
    change = {"type": "added", "object": None, "pose": pose.tolist(), "unidentified": True}
    return {"changes": [{**change, "distractor": "column"}, {"type": "removed", "object": "x"}]}


def test_a_distractor_is_right_only_when_unidentified() -> None:
    truth = _truth((0.3, -0.2))
    near = (0.3 + 0.05, -0.2)
    (row,) = score_distractors(truth, [_found(None, near, 4), _found("mug", (2.0, 2.0), 5)])
    assert row["outcome"] == "unidentified" and row["cluster"] == 4
    (row,) = score_distractors(truth, [_found("padlock", near, 6)])
    assert row["outcome"] == "identified" and row["identified_as"] == "padlock"
    far = (0.3 + 0.16 + DISTRACTOR_REACH_M + 0.01, -0.2)
    (row,) = score_distractors(truth, [_found(None, far, 7)])
    assert row["outcome"] == "missed"


def test_set_report_names_the_set_and_its_variants(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    calls: list[tuple[str, Any, str]] = []

    def fake_run(
        work: Path, scenario: str, seed: int, synth: Any, tag: str, *rest: Any
    ) -> dict[str, Any]:
        calls.append((scenario, synth, tag))
        if "multiple" in tag:
            raise RuntimeError("reconstruction failed")
        distractors = [{"distractor": d, "outcome": "unidentified"} for d in synth.distractors]
        ours = {"changes": [], "false_changes": [], "unidentified": 0, "distractors": distractors}
        return {"ours": ours, "timings_s": {}}

    monkeypatch.setattr(scenarios_bench, "run_scenario", fake_run)
    monkeypatch.setattr(scenarios_bench, "prepared_models", lambda names: ({}, {}))
    out = tmp_path / "scenarios_test.json"
    code = scenarios_bench.main(["--set", "test", "--real-camera", "--out", str(out)])
    report = json.loads(out.read_text())
    assert code == 1  # the failing world is reported, the others kept
    assert report["set"] == "test" and "tuning set" in report["rule"]
    assert set(report["variants"]) == {"ideal_camera", "real_camera"}
    for variant in report["variants"].values():
        assert set(variant["scenarios"]) == {w.name for w in TEST}
        assert "error" in variant["scenarios"]["multiple"]
        assert variant["summary"]["distractors_unidentified"] == 2
    real = [synth for _, synth, tag in calls if "_real_camera_" in tag]
    ideal = [synth for _, synth, tag in calls if "_ideal_camera_" in tag]
    assert len(real) == len(ideal) == len(TEST)
    assert all(s.effects.active for s in real) and not any(s.effects.active for s in ideal)
    assert len({tag for _, _, tag in calls}) == 2 * len(TEST)


def test_a_subset_of_worlds_keeps_each_worlds_lens(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    synths: dict[str, Any] = {}  # "<set>_<world>_<variant>" → its generator options

    def fake_run(
        work: Path, scenario: str, seed: int, synth: Any, tag: str, *rest: Any
    ) -> dict[str, Any]:
        synths[tag.rsplit("_", 1)[0]] = synth
        return {"ours": {"changes": [], "false_changes": [], "unidentified": 0}, "timings_s": {}}

    monkeypatch.setattr(scenarios_bench, "run_scenario", fake_run)
    monkeypatch.setattr(scenarios_bench, "prepared_models", lambda names: ({}, {}))
    out = tmp_path / "subset.json"
    wanted = ["box_swapped_for_bottle", "flat_removed"]
    argv = ["--set", "test", "--real-camera", "--worlds", ",".join(wanted), "--out", str(out)]
    assert scenarios_bench.main(argv) == 0
    report = json.loads(out.read_text())
    assert report["worlds"] == ["flat_removed", "box_swapped_for_bottle"]  # the set's order
    for variant in report["variants"].values():
        assert set(variant["scenarios"]) == set(wanted)
    for name in wanted:
        index = [w.name for w in TEST].index(name)
        world = TEST[index]
        expected = real_camera(world.options(PRESETS["bench"]), index)
        assert synths[f"test_{name}_real_camera"].effects == expected.effects
        assert not synths[f"test_{name}_ideal_camera"].effects.active
    assert scenarios_bench.main(["--set", "test", "--worlds", "flat_removed,nope"]) == 2
    assert "nope" in capsys.readouterr().err


def test_a_cached_cloud_is_reused_only_for_the_same_options_and_stage_code(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    scene_dir = tmp_path / "scene"
    (scene_dir / "before" / "images").mkdir(parents=True)
    (scene_dir / "before" / "images" / "view_000.png").write_bytes(b"png")
    (scene_dir / "reference.json").write_text("{}")
    source = tmp_path / "reconstruct"
    source.mkdir()
    (source / "stage.py").write_text("x = 1\n")
    monkeypatch.setattr(scenarios_bench, "RECONSTRUCT_SOURCE", source)
    built: list[Path] = []

    def fake_reconstruct(images: Path, out: Path, options: Any, *rest: Any) -> Any:
        out.mkdir(parents=True)
        (out / "cloud.ply").write_bytes(b"ply")
        (out / "quality.json").write_text(json.dumps({"points": 1}))
        built.append(out)
        return SimpleNamespace(quality={"points": 1})

    monkeypatch.setattr(scenarios_bench, "reconstruct", fake_reconstruct)

    def capture() -> tuple[Path, bool]:
        out, _, cached = scenarios_bench.reconstruct_capture(
            tmp_path / "work", scene_dir, "before", "default", None
        )
        return out, cached

    first, cached = capture()
    assert not cached and capture() == (first, True)
    (source / "stage.py").write_text("x = 2\n")  # the stage's code changed: built again
    second, cached = capture()
    assert not cached and second != first
    defaults = scenarios_bench.options_from_preset
    monkeypatch.setattr(  # a changed default: built again
        scenarios_bench,
        "options_from_preset",
        lambda preset, **kw: defaults(preset, **kw, point_stride=1),
    )
    third, cached = capture()
    assert not cached and third not in (first, second) and len(built) == 3
