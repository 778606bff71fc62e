"""Pose options: built from a job's JSON, checked by the API against the generated schema,
and passed by the comparison job to the pose step."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from app.core import change_clusters
from app.core.errors import InvalidInput
from app.core.options import check_environment_options, check_stage_options
from workers import comparison as comparison_glue
from workers.pipeline.compare.options import options_from_json
from workers.pipeline.errors import InputError
from workers.pipeline.pose.options import POSE_PRESETS, pose_options_from_json


def test_pose_options_from_json_applies_preset_and_overrides() -> None:
    assert pose_options_from_json(None) == POSE_PRESETS["default"]
    got = pose_options_from_json({"preset": "fast", "n_seeds": 4, "icp_scales_voxels": [1.0, 0.5]})
    assert got == dataclasses.replace(POSE_PRESETS["fast"], n_seeds=4, icp_scales_voxels=(1.0, 0.5))
    with pytest.raises(InputError, match="unknown pose preset 'slow'"):
        pose_options_from_json({"preset": "slow"})
    with pytest.raises(InputError, match="n_seed"):
        pose_options_from_json({"n_seed": 4})


def test_every_pose_preset_written_out_passes_the_api_check() -> None:
    for name, opts in POSE_PRESETS.items():
        full = {
            k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(opts).items()
        }
        check_stage_options("compare", {"pose": {"preset": name, **full}})
        assert pose_options_from_json(full) == opts


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"pose": {"n_seed": 4}}, "options.pose: unknown pose option(s) n_seed"),
        ({"pose": {"n_seeds": "4"}}, "options.pose.n_seeds must be an integer"),
        ({"pose": {"preset": "slow"}}, "options.pose.preset: unknown pose preset"),
        ({"pose": [1]}, "options.pose must be an object"),
    ],
)
def test_a_bad_pose_option_is_refused_naming_it(options: dict[str, Any], message: str) -> None:
    with pytest.raises(InvalidInput, match=re.escape(message)):
        check_stage_options("compare", options)
    with pytest.raises(InvalidInput, match=r"options\.compare\.pose"):
        check_environment_options({"compare": options})


def test_the_comparison_job_passes_the_posted_pose_options_to_the_pose_step(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """workers/comparison.py takes ``pose`` out of the comparison's options (the compare
    stage gets the rest) and hands it to :func:`pose_changes`."""
    posted = {
        "preset": "thesis",
        "cluster_min_points": 40,
        "pose": {"preset": "fast", "n_seeds": 4},
    }
    inputs = SimpleNamespace(
        options=posted,
        before=None,
        after=None,
        twin=[],
        classes=["box"],
        models={},
        folder="snapshots/s/comparisons/c",
    )
    seen: dict[str, Any] = {}

    def fake_compare(*args: Any) -> str:
        seen["compare_options"] = args[5]
        return "result"

    def fake_pose_changes(*args: Any) -> list[dict[str, Any]]:
        seen["pose_options"] = args[6]
        return []

    monkeypatch.setattr(comparison_glue, "_load", lambda ctx: inputs)
    monkeypatch.setattr(comparison_glue, "_capture_data", lambda ctx, files: None)
    monkeypatch.setattr(comparison_glue, "compare_snapshots", fake_compare)
    monkeypatch.setattr(comparison_glue, "pose_changes", fake_pose_changes)
    monkeypatch.setattr(comparison_glue, "clusters_npz", lambda result: b"npz")
    monkeypatch.setattr(
        comparison_glue,
        "publish",
        lambda ctx, root, files: seen.setdefault("published", (root, sorted(files))),
    )
    ctx = SimpleNamespace(progress=lambda stage, fraction: None, work_dir=tmp_path)
    comparison_glue._compute(ctx)  # type: ignore[arg-type]
    assert seen["pose_options"] == {"preset": "fast", "n_seeds": 4}
    assert seen["compare_options"] == options_from_json("thesis", {"cluster_min_points": 40})
    assert seen["published"] == (inputs.folder, [change_clusters.FILE])
