"""The symmetry group's JSON forms and the pose error modulo the group
(workers.pipeline.model.symmetry_group)."""

from __future__ import annotations

import numpy as np
import pytest

from workers.pipeline.errors import InputError
from workers.pipeline.geometry import axis_angle_matrix, make_rigid
from workers.pipeline.model.symmetry_group import (
    rotation_about,
    spec_from_ground_truth,
    spec_to_json,
    symmetric_pose_error,
)
from workers.pipeline.pose import random_rigid
from workers.pipeline.synth.symmetry import symmetric_pose_error as sampled_pose_error


def test_ground_truth_spelling_reads_as_the_spec() -> None:
    assert spec_from_ground_truth(None).kind == "none"
    drum = spec_from_ground_truth({"kind": "continuous", "axis": [0, 0, 2], "point": [0.05, 0, 0]})
    assert drum.kind == "continuous"
    np.testing.assert_allclose(drum.axis, [0, 0, 1])
    np.testing.assert_allclose(drum.origin, [0.05, 0, 0])
    flip = make_rigid(axis_angle_matrix([1, 0, 0], np.pi), (0, 0, 0))
    box = spec_from_ground_truth({"kind": "discrete", "transforms": [flip.tolist()]})
    assert spec_to_json(box)["kind"] == "discrete" and len(box.rotations) == 2
    with pytest.raises(InputError):
        spec_from_ground_truth({"kind": "discrete", "transforms": [np.eye(3).tolist()]})
    with pytest.raises(InputError):
        spec_from_ground_truth([1, 2])


@pytest.mark.parametrize("seed", range(5))
def test_closed_form_error_agrees_with_the_sampled_one(seed: int) -> None:
    """The closed-form rotation error modulo a continuous symmetry equals the minimum over
    the ground truth's 0.5° samples within their resolution (≤ 0.25°), and an exactly
    turned pose has no error."""
    rng = np.random.default_rng(seed)
    raw = {"kind": "continuous", "axis": [0.0, 0.0, 1.0], "point": [0.02, 0.0, 0.0]}
    spec = spec_from_ground_truth(raw)
    true = random_rigid(rng, 0.5)
    turned = true @ rotation_about(spec.axis, rng.uniform(0, 2 * np.pi), spec.origin)
    # arccos near 1 turns float rounding into ~1e-6°
    assert symmetric_pose_error(turned, true, spec) == pytest.approx((0.0, 0.0), abs=1e-5)
    tilt = make_rigid(axis_angle_matrix(rng.normal(size=3), np.radians(10.0)), (0.0, 0.0, 0.0))
    estimate = turned @ tilt
    _, closed = symmetric_pose_error(estimate, true, spec)
    _, sampled = sampled_pose_error(estimate, true, raw)
    assert closed <= sampled + 1e-9 and sampled - closed <= 0.25
