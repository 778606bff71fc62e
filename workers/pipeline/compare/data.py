"""Typed inputs of the compare stage: captures, cameras, detections and the twin state.

Frames: every point and pose is in the environment frame (``env``), metres; cameras use
OpenCV axes (x right, y down, z forward). Constructors check shapes and raise
:class:`~workers.pipeline.errors.ShapeError`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from workers.pipeline.errors import ShapeError
from workers.pipeline.geometry import as_mat4, as_points

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


def as_detections(rows: ArrayLike, name: str = "detections") -> FloatArray:
    """YOLO rows as an (M, 6) float64 array ``class_id, cx, cy, w, h, confidence``.

    Input is (M, 5) or (M, 6), coordinates normalised to 0..1 of the image size; a missing
    confidence becomes 1. Raises ShapeError on other shapes or non-finite values.
    """
    arr = np.asarray(rows, dtype=np.float64)
    if arr.size == 0:
        return np.zeros((0, 6))
    if arr.ndim != 2 or arr.shape[1] not in (5, 6):
        raise ShapeError(f"{name} must be (M, 5) or (M, 6), got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ShapeError(f"{name} contains non-finite values")
    if arr.shape[1] == 5:
        arr = np.column_stack([arr, np.ones(len(arr))])
    return arr


@dataclass(frozen=True, eq=False)
class Camera:
    """One calibrated image: ``k`` (3, 3) pixels, image ``width`` × ``height`` pixels,
    ``cam_from_env`` (4, 4) rigid, metres, OpenCV axes, and the lens's OpenCV
    ``distortion`` (k1, k2, p1, p2, k3), used only to undistort the photo itself
    (detections and projections take the pinhole part)."""

    name: str
    k: FloatArray
    width: int
    height: int
    cam_from_env: FloatArray
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        k = np.asarray(self.k, dtype=np.float64)
        if k.shape != (3, 3) or not np.all(np.isfinite(k)) or k[0, 0] <= 0 or k[1, 1] <= 0:
            raise ShapeError(f"camera {self.name!r}: K must be a finite 3×3 with fx, fy > 0")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ShapeError(f"camera {self.name!r}: width and height must be positive")
        object.__setattr__(self, "k", k)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        object.__setattr__(
            self, "cam_from_env", as_mat4(self.cam_from_env, f"{self.name}.cam_from_env")
        )


@dataclass(frozen=True, eq=False)
class CaptureData:
    """One snapshot as the compare stage sees it.

    ``points_env`` (N, 3) float64 metres in the environment frame; ``colors`` (N, 3) or None;
    ``cameras`` the capture's calibrated images; ``detections`` maps an image name to its
    YOLO rows (see :func:`as_detections`; a missing name means no detections);
    ``alignment_residual_m`` the residual of aligning this capture to the environment frame
    (used by the level-of-detection threshold); ``photos`` maps an image name to its file
    (read only to check what the cameras saw against the cloud's colours; a missing name
    means no such check for that camera).
    """

    points_env: FloatArray
    cameras: tuple[Camera, ...] = ()
    detections: Mapping[str, FloatArray] = field(default_factory=dict)
    colors: FloatArray | None = None
    alignment_residual_m: float = 0.0
    photos: Mapping[str, Path] = field(default_factory=dict)

    def __post_init__(self) -> None:
        pts = as_points(self.points_env, "points_env")
        if not np.all(np.isfinite(pts)):
            raise ShapeError("points_env contains non-finite values")
        object.__setattr__(self, "points_env", pts)
        object.__setattr__(self, "cameras", tuple(self.cameras))
        names = [c.name for c in self.cameras]
        if len(set(names)) != len(names):
            raise ShapeError("camera names must be unique")
        dets = {str(k): as_detections(v, f"detections[{k!r}]") for k, v in self.detections.items()}
        object.__setattr__(self, "detections", dets)
        if self.colors is not None:
            col = np.asarray(self.colors, dtype=np.float64)
            if col.shape != pts.shape:
                raise ShapeError(f"colors must be {pts.shape}, got {col.shape}")
            object.__setattr__(self, "colors", col)
        if not np.isfinite(self.alignment_residual_m) or self.alignment_residual_m < 0:
            raise ShapeError("alignment_residual_m must be finite and ≥ 0")


@dataclass(frozen=True, eq=False)
class TwinInstance:
    """An object instance of the twin as it stands before the comparison.

    ``object_name`` is the library/detector class name; ``env_from_object`` (4, 4);
    ``centroid_env`` (3,) metres, the centre of the instance's geometry in the environment
    frame (defaults to the pose's translation).
    """

    instance_id: str
    object_name: str
    env_from_object: FloatArray
    centroid_env: FloatArray | None = None

    def __post_init__(self) -> None:
        pose = as_mat4(self.env_from_object, f"{self.instance_id}.env_from_object")
        object.__setattr__(self, "env_from_object", pose)
        c = pose[:3, 3].copy() if self.centroid_env is None else self.centroid_env
        c = np.asarray(c, dtype=np.float64).reshape(-1)
        if c.shape != (3,) or not np.all(np.isfinite(c)):
            raise ShapeError(f"{self.instance_id}: centroid_env must be a finite (3,)")
        object.__setattr__(self, "centroid_env", c)

    @property
    def centroid(self) -> FloatArray:
        """(3,) centroid in the environment frame, metres."""
        assert self.centroid_env is not None  # set in __post_init__
        return self.centroid_env
