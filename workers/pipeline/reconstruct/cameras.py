"""The reconstruct stage's cameras: cameras.json read and written through the one format
(:mod:`app.formats.cameras`), and the numpy-side camera types its modules share.

Intrinsics follow OpenCV's pixel convention: the centre of the top-left pixel is (0, 0).
COLMAP puts it at (0.5, 0.5); :func:`Intrinsics.colmap_params` and
:func:`intrinsics_from_colmap` convert.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from app.formats import FormatError
from app.formats.cameras import (
    CAMERA_MODELS,
    Camera,
    CamerasFile,
    load_cameras_file,
    pose_rows,
    read_cameras,
)
from app.formats.cameras import write_cameras as write_cameras_file
from workers.pipeline.errors import InputError
from workers.pipeline.geometry import Mat4, as_mat4, invert_rigid


@dataclass(frozen=True)
class Intrinsics(Camera):
    """A camera model as in cameras.json (:class:`app.formats.cameras.Camera`: COLMAP model
    name, image size in pixels, params) with its numpy forms. InputError when the model is
    not one every stage can use or the params do not fit it."""

    def __post_init__(self) -> None:
        try:
            super().__post_init__()
        except FormatError as exc:
            raise InputError(exc.problem) from exc

    @classmethod
    def of(cls, camera: Camera) -> Intrinsics:
        return cls(camera.model, camera.width, camera.height, tuple(camera.params))

    @property
    def k_matrix(self) -> NDArray[np.float64]:
        """(3, 3) intrinsic matrix, pixels, OpenCV convention."""
        fx, fy, cx, cy = self.pinhole
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> NDArray[np.float64]:
        """(5,) OpenCV distortion coefficients (k1, k2, p1, p2, k3)."""
        return np.array(self.distortion, dtype=np.float64)

    def colmap_params(self) -> list[float]:
        """Params in COLMAP's pixel convention (principal point shifted by +0.5 px)."""
        out = list(self.params)
        icx, icy = CAMERA_MODELS[self.model].principal_point
        out[icx] += 0.5
        out[icy] += 0.5
        return out


def intrinsics_from_colmap(model: str, width: int, height: int, params: list[float]) -> Intrinsics:
    """Inverse of :meth:`Intrinsics.colmap_params`: COLMAP params to OpenCV convention."""
    out = [float(v) for v in params]
    if model in CAMERA_MODELS:
        icx, icy = CAMERA_MODELS[model].principal_point
        out[icx] -= 0.5
        out[icy] -= 0.5
    return Intrinsics(model, int(width), int(height), tuple(out))


@dataclass(frozen=True)
class CamerasSpec:
    """Parsed cameras.json: shared or per-image intrinsics, and optional env_from_cam poses
    (4×4 float64, metres, OpenCV axes)."""

    intrinsics: Intrinsics | None = None
    intrinsics_per_image: dict[str, Intrinsics] = field(default_factory=dict)
    poses: dict[str, Mat4] = field(default_factory=dict)

    @classmethod
    def of(cls, cameras: CamerasFile) -> CamerasSpec:
        """The numpy form of the shared reader's output."""
        shared = None if cameras.intrinsics is None else Intrinsics.of(cameras.intrinsics)
        return cls(
            shared,
            {name: Intrinsics.of(c) for name, c in cameras.intrinsics_per_image.items()},
            {name: as_mat4(m, f"poses[{name}]") for name, m in cameras.poses.items()},
        )

    def intrinsics_for(self, image_name: str) -> Intrinsics | None:
        """The intrinsics of one image, or None when cameras.json does not give them."""
        return self.intrinsics_per_image.get(image_name, self.intrinsics)

    def has_all_poses(self, image_names: list[str]) -> bool:
        return bool(image_names) and all(n in self.poses for n in image_names)

    def has_all_intrinsics(self, image_names: list[str]) -> bool:
        return bool(image_names) and all(self.intrinsics_for(n) is not None for n in image_names)


def parse_cameras(raw: Any) -> CamerasSpec:
    """Parse a cameras.json document (:func:`app.formats.cameras.read_cameras`); InputError
    naming the field on malformed content."""
    try:
        return CamerasSpec.of(read_cameras(raw))
    except FormatError as exc:
        raise InputError(str(exc)) from exc


def load_cameras(path: Path) -> CamerasSpec:
    """Read and parse a cameras.json file; InputError when unreadable or malformed."""
    try:
        return CamerasSpec.of(load_cameras_file(Path(path)))
    except FormatError as exc:
        raise InputError(str(exc)) from exc


@dataclass(frozen=True)
class CameraView:
    """One calibrated, posed image. ``env_from_cam`` 4×4 rigid, metres, OpenCV axes.

    In structure from motion's own frame (before the environment frame is fixed) the same
    type carries ``world_from_cam`` in that field; :func:`with_pose` swaps it.
    """

    name: str
    intrinsics: Intrinsics
    env_from_cam: Mat4

    @property
    def cam_from_env(self) -> Mat4:
        return invert_rigid(self.env_from_cam)

    @property
    def centre(self) -> NDArray[np.float64]:
        return np.asarray(self.env_from_cam[:3, 3], dtype=np.float64)

    def with_pose(self, env_from_cam: Mat4) -> CameraView:
        return CameraView(self.name, self.intrinsics, as_mat4(env_from_cam, "env_from_cam"))


def cameras_file(views: Sequence[CameraView]) -> CamerasFile:
    """The cameras.json of posed views: per-image intrinsics and env_from_cam poses, the
    format the next stage (compare) reads."""
    return CamerasFile(
        intrinsics=None,
        intrinsics_per_image={v.name: Camera(*_fields(v.intrinsics)) for v in views},
        poses={v.name: pose_rows(v.env_from_cam.tolist()) for v in views},
    )


def write_cameras(path: Path, views: Sequence[CameraView]) -> None:
    """Write the cameras.json of posed views (:func:`cameras_file`) to ``path``."""
    write_cameras_file(path, cameras_file(views))


def _fields(intr: Intrinsics) -> tuple[str, int, int, tuple[float, ...]]:
    return intr.model, intr.width, intr.height, tuple(float(p) for p in intr.params)
