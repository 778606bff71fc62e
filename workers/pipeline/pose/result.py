"""What pose estimation returns: :class:`PoseResult`, with the :class:`Trial` candidates."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from workers.pipeline.geometry import Mat4


@dataclass(frozen=True)
class Trial:
    """One global-registration candidate after its short ICP polish."""

    source: str
    score: float
    fitness: float
    inlier_rmse_m: float
    seconds: float
    env_from_object: Mat4


@dataclass(frozen=True, eq=False)
class Alternative:
    """Another refined hypothesis: its fine ``score`` and ``env_from_object`` (4×4, metres)."""

    score: float
    env_from_object: Mat4


#: the ``pose_quality`` figures the pose step measures of its own chosen pose only
CHOICE_FIGURES = ("cluster_coverage", "runner_up_ratio", "rotation_slack_deg", "final_turn_deg")


@dataclass(frozen=True, eq=False)
class PoseResult:
    """Pose of one object. ``env_from_object``: 4×4 float64 mapping object-model points
    (metres) into the environment frame. ``equivalent_poses``: other poses that fit equally
    well by symmetry (continuous symmetry: 8 samples per discrete element; the axis is
    ``symmetry_axis_env`` through ``symmetry_origin_env``). ``chosen_by``: "unique",
    "colour", "previous" or "up". ``cluster_coverage`` is None when no cluster points were given.
    ``alternatives``: the other refined hypotheses (:class:`Alternative`), best
    first, a near-tie at its finished pose — for a caller whose re-projection check
    rejects the chosen pose.
    ``rotation_slack_deg``: the rotation the scan's residual level hides
    (:func:`~workers.pipeline.pose.fit.rotation_slack_deg`); ``final_turn_deg``: how far the
    last fit turned the refinement's ICP pose, modulo symmetry (both 0 when not computed);
    ``settled_by_outline``: (the chosen pose's outline cost per scan point, the best
    near-tie's) when a flat object's outline settled its near-ties, else None.
    ``righted``: an upright pose was published over an upside-down one that scored better
    (``PoseOptions.upright_ratio``): the scan preferred the other way up."""

    env_from_object: Mat4
    fitness: float
    inlier_rmse_m: float
    inlier_distance_m: float
    score: float
    runner_up_score: float
    cluster_coverage: float | None
    verified: bool
    rejections: tuple[str, ...]
    ambiguous: bool
    equivalent_poses: tuple[Mat4, ...]
    symmetry_axis_env: NDArray[np.float64] | None
    symmetry_origin_env: NDArray[np.float64] | None
    chosen_by: str
    source: str
    trials: tuple[Trial, ...]
    n_scene_points: int
    alternatives: tuple[Alternative, ...] = ()
    rotation_slack_deg: float = 0.0
    final_turn_deg: float = 0.0
    settled_by_outline: tuple[float, float] | None = None
    righted: bool = False
    timings_s: dict[str, float] = field(default_factory=dict)

    def quality_json(self) -> dict[str, Any]:
        """The ``pose_quality`` object of the comparison contract: the verification's figures
        (``runner_up_ratio``: the best distinct pose's score over this one's) with the verdict."""
        out: dict[str, Any] = {
            "fitness": self.fitness,
            "inlier_rmse": self.inlier_rmse_m,
            "cluster_coverage": self.cluster_coverage,
            "runner_up_ratio": self.runner_up_score / self.score if self.score > 0 else 0.0,
            "rotation_slack_deg": self.rotation_slack_deg,
            "final_turn_deg": self.final_turn_deg,
            "verified": self.verified,
            "ambiguous": self.ambiguous,
            "equivalent_poses": [p.tolist() for p in self.equivalent_poses],
        }
        if self.settled_by_outline is not None:
            cost, rival = self.settled_by_outline
            out["settled_by_outline"] = {
                "outline_cost": round(cost, 4),
                "best_rival": round(rival, 4),
            }
        return out
