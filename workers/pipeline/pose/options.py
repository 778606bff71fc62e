"""Pose estimation settings: :class:`PoseOptions` and its named presets.

Distances are in units of the model's feature voxel ``v`` (``diameter / voxel_divisor``, see
:class:`~workers.pipeline.model.ModelOptions`) unless the name ends in ``_m`` (metres).
Measurement history behind the defaults: ``docs/decisions/pose.md``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from workers.pipeline.errors import InputError
from workers.pipeline.option_values import with_overrides

#: the kinds of the last fit (``PoseOptions.final_fit``)
FINAL_FITS = ("scene_to_model", "icp")


@dataclass(frozen=True)
class PoseOptions:
    """Pose estimation settings (one line each: meaning, unit, when to change it)."""

    # crop radius around the cluster, × model diameter; raise when clusters are far off-centre
    crop_factor: float = 0.7
    # RANSAC seeds per round; raise for hard views (clutter, little overlap), costs time
    n_seeds: int = 5
    # seeds always run per round before stopping early when two starts agree; lower is faster
    min_seeds: int = 2
    # RANSAC iterations per seed; raise when good matches are rare (little overlap)
    ransac_max_iterations: int = 20000
    # RANSAC early-stop confidence in [0, 1]; rarely changed
    ransac_confidence: float = 0.999
    # RANSAC inlier distance, voxels; raise for noisy scans
    ransac_distance_voxels: float = 1.5
    # RANSAC edge-length similarity check in (0, 1]; lower accepts more distorted matches
    edge_length_check: float = 0.9
    # truncation distance of the candidate score, voxels; rarely changed
    score_voxels: float = 0.5
    # distinct candidates refined per round; raise when the right pose ranks low coarsely
    n_refine: int = 3
    # best candidates also tried turned 180° and by near-symmetries; raise for elongated objects
    n_flip_bases: int = 2
    # rounds of new seeds while the pose is not verified; raise for hard views, costs time
    max_rounds: int = 2
    # truncation distance of the refined score, voxels; lower separates near-symmetric poses
    fine_score_voxels: float = 0.3
    # ICP distance scales, voxels, coarse to fine; the first two also polish every candidate
    icp_scales_voxels: tuple[float, ...] = (1.5, 0.6, 0.25)
    # ICP iterations per scale of the refinement; raise if refinement has not converged
    icp_max_iterations: int = 20
    # last fit of the winner: "icp" (point-to-plane ICP at the last ICP scale, model onto
    # the scan) or "scene_to_model" (that ICP, then the scan fitted robustly onto the
    # model's tangent planes, kept unless it turned the ICP's pose by max_final_turn_deg)
    final_fit: str = "scene_to_model"
    # reach of the last fit, voxels (capped by max_inlier_distance_m); ≥ the scan's noise
    final_reach_voxels: float = 1.0
    # iterations of the last fit; it stops earlier once the pose is still
    final_max_iterations: int = 30
    # inlier distance of ``fitness``, voxels (capped by ``max_inlier_distance_m``)
    inlier_voxels: float = 0.5
    # least inlier distance of ``fitness``, in the scan's median point spacings about the
    # object: a small object's half voxel is finer than the scan; 0 = voxels alone
    inlier_spacings: float = 1.5
    # cap on every inlier distance, metres: the scan's noise, not the object's size
    max_inlier_distance_m: float = 0.01
    # least share of model points near the scene for ``verified``; one view sees 30-60 %
    min_fitness: float = 0.25
    # least tolerance of cluster coverage, voxels (3σ of the cluster's scatter, clipped)
    coverage_voxels: float = 0.5
    # largest tolerance of cluster coverage, voxels (and at most max_inlier_distance_m)
    max_coverage_voxels: float = 1.5
    # least share of cluster points the posed model explains (near its surface or inside
    # its convex hull) for ``verified``
    min_cluster_coverage: float = 0.85
    # colour correlation margin that picks a symmetric object's equivalent pose (a label)
    colour_margin: float = 0.02
    # support-plane band, voxels (≤ max_inlier_distance_m): removed, penalised below; 0 = off
    support_band_voxels: float = 0.5
    # a final pose sunk up to this far into its support is lifted onto it, metres; 0 disables;
    # keep it well under the height between two supports (a table above the floor)
    max_sink_m: float = 0.02
    # a final pose within max_sink_m of its support whose base (else a hull face it can rest
    # on) nearest the plane is tilted at most this much, degrees, is set flat on it (turn
    # and shift across it refitted); 0 disables; lower where objects lean on things
    rest_max_tilt_deg: float = 10.0
    # a final pose touching its support on nothing it could rest on (its nearest resting
    # face tilted past rest_max_tilt_deg) is set down on it, unverified, up to this tilt,
    # degrees; tilted more, something holds it; ≤ rest_max_tilt_deg disables
    max_set_down_tilt_deg: float = 20.0
    # an object resting on its support at most this tall, × its diameter, takes its turn on
    # it and shift across it from its outline seen from above (top_view.py); 0 disables
    top_view_max_height_ratio: float = 0.5
    # cap on the outline distances of that fit, voxels; ≥ the scan's noise at the outline
    top_view_reach_voxels: float = 2.0
    # the scan's points within this of the outline take part in that fit, voxels; raise
    # when flat poses start further off (the points are chosen again around the fit)
    top_view_window_voxels: float = 4.0
    # cap on the pixel distance from its silhouette to a photo's edge; ≥ the pose step's
    # error seen in the photos, ≤ the spacing of the support's own texture edges
    photo_edges_cap_px: float = 4.0
    # every pose is turned on its support and shifted across it onto the edges of at most
    # this many photos (those showing the object largest; photo_edges.py); 0 disables
    photo_edges_max_views: int = 12
    # the photos' fit turning the pose by at most this, degrees, confirms the pose step's
    # last fit where it and the ICP disagree (max_final_turn_deg); lower confirms fewer
    photo_edges_confirm_deg: float = 2.0
    # largest rotation the scan's residual level may hide, degrees, for ``verified``
    # (rotation_slack_deg; only with final_fit "scene_to_model"); lower verifies fewer
    max_rotation_slack_deg: float = 20.0
    # largest turn of the scan-to-model fit from the ICP's pose, degrees, for ``verified``
    # and to keep that fit (final_turn_deg: the fits disagree where the scan is deformed)
    max_final_turn_deg: float = 3.0
    # a distinct pose scoring above this × the best makes the pose unverified (ambiguous)
    max_runner_up_ratio: float = 0.85
    # an upright pose resting on its support that scores at least this × an upside-down
    # best is taken instead (unverified): where stereo closes a hollow object's opening
    # the scan barely tells up from down; lower prefers the library's up more
    upright_ratio: float = 0.7
    # a flat pose's outline seen from above chooses among its near-ties: the least-cost
    # one when the best-scoring costs more than this × it per scan point, settled when
    # every other does; 0 disables; lower settles more
    outline_settle_ratio: float = 1.25
    # seed of RANSAC and the support-plane search: one seed, one result
    seed: int = 0
    # objects posed at once, on threads (0: one per core); the poses do not depend on it
    threads: int = 0

    def __post_init__(self) -> None:
        for name in ("inlier_spacings", "photo_edges_max_views", "threads"):
            if getattr(self, name) < 0:
                raise InputError(f"pose option {name} must be ≥ 0")


POSE_PRESETS: dict[str, PoseOptions] = {
    "default": PoseOptions(),
    "fast": PoseOptions(n_seeds=3, ransac_max_iterations=10000, max_rounds=1),
    "thorough": PoseOptions(n_seeds=8, ransac_max_iterations=100000, max_rounds=4),
}


def pose_options_from_json(options: Mapping[str, Any] | None) -> PoseOptions:
    """Options from a job's ``{"preset": name, **overrides}`` (the ``pose`` section of the
    comparison options; lists become tuples). InputError for an unknown preset or option."""
    overrides = dict(options or {})
    preset = str(overrides.pop("preset", "default"))
    return with_overrides("pose", POSE_PRESETS, preset, overrides)
