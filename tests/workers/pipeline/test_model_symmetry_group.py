"""The symmetry group's JSON forms and the pose error modulo the group
(workers.pipeline.model.symmetry_group)."""

from __future__ import annotations

import numpy as np
import pytest

from workers.pipeline.errors import InputError
from workers.pipeline.geometry import axis_angle_matrix, make_rigid, pose_error
from workers.pipeline.model.symmetry_group import (
    rotation_about,
    spec_from_json,
    spec_to_json,
    symmetric_pose_error,
)
from workers.pipeline.pose import random_rigid
from workers.pipeline.synth import builtin_models


def test_generated_scenes_write_the_library_format() -> None:
    """A generated object's symmetry (ground_truth.json) is read by the one reader, and
    the reader refuses what is not a spec."""
    drum = next(m for m in builtin_models() if m.symmetry is not None)
    spec = spec_from_json(drum.symmetry)
    assert spec.kind == "continuous"
    np.testing.assert_allclose(spec.axis, [0, 0, 1])
    flip = make_rigid(axis_angle_matrix([1, 0, 0], np.pi), (0, 0, 0))
    box = spec_from_json({"kind": "discrete", "rotations": [flip.tolist()]})
    assert spec_to_json(box)["kind"] == "discrete" and len(box.rotations) == 2
    with pytest.raises(InputError):
        spec_from_json({"kind": "discrete", "rotations": [np.eye(3).tolist()]})
    with pytest.raises(InputError):
        spec_from_json([1, 2])
    with pytest.raises(InputError, match="unknown keys"):  # an old spelling is no origin
        spec_from_json({"kind": "continuous", "axis": [0, 0, 1], "point": [0.05, 0, 0]})


def _sampled_error(
    estimate: np.ndarray, true: np.ndarray, axis: np.ndarray, origin: np.ndarray
) -> tuple[float, float]:
    """Brute-force oracle: the smallest pose error over turns about the axis every 0.5°."""
    turns = [rotation_about(axis, a, origin) for a in np.radians(np.arange(0.0, 360.0, 0.5))]
    return min((pose_error(estimate, true @ t) for t in turns), key=lambda e: (e[1], e[0]))


@pytest.mark.parametrize("seed", range(5))
def test_closed_form_error_agrees_with_the_sampled_one(seed: int) -> None:
    """The closed-form rotation error modulo a continuous symmetry equals the minimum over
    the ground truth's 0.5° samples within their resolution (≤ 0.25°), and an exactly
    turned pose has no error."""
    rng = np.random.default_rng(seed)
    spec = spec_from_json({"kind": "continuous", "axis": [0, 0, 1], "origin": [0.02, 0, 0]})
    true = random_rigid(rng, 0.5)
    turned = true @ rotation_about(spec.axis, rng.uniform(0, 2 * np.pi), spec.origin)
    # arccos near 1 turns float rounding into ~1e-6°
    assert symmetric_pose_error(turned, true, spec) == pytest.approx((0.0, 0.0), abs=1e-5)
    tilt = make_rigid(axis_angle_matrix(rng.normal(size=3), np.radians(10.0)), (0.0, 0.0, 0.0))
    estimate = turned @ tilt
    _, closed = symmetric_pose_error(estimate, true, spec)
    _, sampled = _sampled_error(estimate, true, spec.axis, spec.origin)
    assert closed <= sampled + 1e-9 and sampled - closed <= 0.25
