"""Pose of a library object in the environment: ``env_from_object`` (4×4, metres).

One module per step of :func:`estimate_pose` (see :mod:`~workers.pipeline.pose.estimate`):
``crop`` (scene region), ``candidates`` (global candidates), ``refine`` (ICP refinement),
``verify`` (3D verification and the re-projection check), ``canonical`` (one pose among
symmetric equivalents); ``fit`` holds the ICP and scores they share, ``options`` the
settings, ``posing`` poses a comparison's changes, ``cli`` the command line.
"""

from workers.pipeline.model.symmetry_group import symmetric_pose_error
from workers.pipeline.pose.candidates import distinct_pose, random_rigid
from workers.pipeline.pose.crop import SceneCloud
from workers.pipeline.pose.estimate import estimate_pose
from workers.pipeline.pose.options import POSE_PRESETS, PoseOptions
from workers.pipeline.pose.result import Alternative, PoseResult, Trial
from workers.pipeline.pose.verify import RUNNER_UP_REASON

__all__ = [
    "POSE_PRESETS",
    "RUNNER_UP_REASON",
    "Alternative",
    "PoseOptions",
    "PoseResult",
    "SceneCloud",
    "Trial",
    "distinct_pose",
    "estimate_pose",
    "random_rigid",
    "symmetric_pose_error",
]
