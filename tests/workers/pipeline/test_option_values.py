"""One way to make a stage's options from a preset and JSON overrides
(workers.pipeline.option_values.with_overrides), used by reconstruct, compare and pose."""

from __future__ import annotations

from typing import Any

import pytest

from workers.pipeline.compare.options import ThresholdSpec, options_from_json
from workers.pipeline.errors import InputError
from workers.pipeline.pose.options import pose_options_from_json
from workers.pipeline.reconstruct.options import options_from_preset


def test_json_values_become_the_fields_types() -> None:
    rec = options_from_preset("default", mvs_scale=1, max_num_features=4096.0, planar_prior=False)
    assert rec.mvs_scale == 1.0 and isinstance(rec.mvs_scale, float)
    assert rec.max_num_features == 4096 and isinstance(rec.max_num_features, int)
    cmp = options_from_json("default", {"threshold": {"kind": "lod"}, "grow_threshold": None})
    assert cmp.threshold == ThresholdSpec(kind="lod") and cmp.grow_threshold is None
    assert options_from_json("thesis", None) == options_from_json("thesis", {})


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: options_from_preset("fastest"), "unknown reconstruct preset 'fastest'"),
        (lambda: options_from_preset(mvs_scal=0.5), "unknown reconstruct options: mvs_scal"),
        (lambda: options_from_preset(planar_prior="yes"), "planar_prior must be of type bool"),
        (lambda: options_from_preset(max_num_features=1.5), "max_num_features must be of type int"),
        (lambda: options_from_preset(sgbm_mode="3-way"), "sgbm_mode must be one of"),
        (lambda: options_from_json("default", {"threshold": 3}), "threshold must be an object"),
        (lambda: options_from_json("default", [1]), "compare options must be an object"),
        (lambda: pose_options_from_json({"preset": "slow"}), "unknown pose preset 'slow'"),
        (lambda: pose_options_from_json({"n_seed": 4}), "unknown pose options: n_seed"),
    ],
)
def test_a_bad_override_is_an_input_error_naming_it(make: Any, message: str) -> None:
    with pytest.raises(InputError, match=message):
        make()


def test_lists_become_tuples_of_floats() -> None:
    pose = pose_options_from_json({"preset": "fast"})
    tuples = [k for k, v in vars(pose).items() if isinstance(v, tuple)]
    if not tuples:
        pytest.fail("PoseOptions has no tuple option to exercise")
    name = tuples[0]
    got = pose_options_from_json({name: [1, 2.5]})
    assert getattr(got, name) == (1.0, 2.5)
    with pytest.raises(InputError, match="must be a list of numbers"):
        pose_options_from_json({name: ["a"]})
