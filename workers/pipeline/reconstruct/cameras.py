"""cameras.json (docs/contract.md) and the per-view camera type shared by the stage's modules.

Intrinsics follow OpenCV's pixel convention: the centre of the top-left pixel is (0, 0).
COLMAP puts it at (0.5, 0.5); :func:`Intrinsics.colmap_params` and
:func:`intrinsics_from_colmap` convert.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from workers.pipeline.errors import InputError, ShapeError
from workers.pipeline.geometry import Mat4, as_mat4, invert_rigid

# model name -> (number of params, index of cx, index of cy)
_MODELS: dict[str, tuple[int, int, int]] = {
    "SIMPLE_PINHOLE": (3, 1, 2),
    "PINHOLE": (4, 2, 3),
    "SIMPLE_RADIAL": (4, 1, 2),
    "RADIAL": (5, 1, 2),
    "OPENCV": (8, 2, 3),
}


@dataclass(frozen=True)
class Intrinsics:
    """A camera model as in cameras.json: COLMAP model name, image size in pixels, params."""

    model: str
    width: int
    height: int
    params: tuple[float, ...]

    def __post_init__(self) -> None:
        if self.model not in _MODELS:
            raise InputError(f"camera model {self.model!r} unsupported; use {', '.join(_MODELS)}")
        if len(self.params) != _MODELS[self.model][0]:
            raise InputError(
                f"{self.model} takes {_MODELS[self.model][0]} params, got {len(self.params)}"
            )
        if self.width <= 0 or self.height <= 0:
            raise InputError(f"image size must be positive, got {self.width}×{self.height}")

    @property
    def k_matrix(self) -> NDArray[np.float64]:
        """(3, 3) intrinsic matrix, pixels, OpenCV convention."""
        p = self.params
        if self.model in {"SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"}:
            fx = fy = p[0]
            cx, cy = p[1], p[2]
        else:
            fx, fy, cx, cy = p[0], p[1], p[2], p[3]
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> NDArray[np.float64]:
        """(5,) OpenCV distortion coefficients (k1, k2, p1, p2, k3)."""
        p = self.params
        out = np.zeros(5)
        if self.model == "SIMPLE_RADIAL":
            out[0] = p[3]
        elif self.model == "RADIAL":
            out[:2] = p[3:5]
        elif self.model == "OPENCV":
            out[:4] = p[4:8]
        return out

    def colmap_params(self) -> list[float]:
        """Params in COLMAP's pixel convention (principal point shifted by +0.5 px)."""
        out = list(self.params)
        _, icx, icy = _MODELS[self.model]
        out[icx] += 0.5
        out[icy] += 0.5
        return out

    def to_json(self) -> dict[str, Any]:
        return {
            "model": self.model,
            "width": self.width,
            "height": self.height,
            "params": list(self.params),
        }


def intrinsics_from_colmap(model: str, width: int, height: int, params: list[float]) -> Intrinsics:
    """Inverse of :meth:`Intrinsics.colmap_params`: COLMAP params to OpenCV convention."""
    out = [float(v) for v in params]
    if model in _MODELS:
        _, icx, icy = _MODELS[model]
        out[icx] -= 0.5
        out[icy] -= 0.5
    return Intrinsics(model, int(width), int(height), tuple(out))


@dataclass(frozen=True)
class CamerasSpec:
    """Parsed cameras.json: shared or per-image intrinsics, and optional env_from_cam poses."""

    intrinsics: Intrinsics | None = None
    intrinsics_per_image: dict[str, Intrinsics] = field(default_factory=dict)
    poses: dict[str, Mat4] = field(default_factory=dict)

    def intrinsics_for(self, image_name: str) -> Intrinsics | None:
        """The intrinsics of one image, or None when cameras.json does not give them."""
        return self.intrinsics_per_image.get(image_name, self.intrinsics)

    def has_all_poses(self, image_names: list[str]) -> bool:
        return bool(image_names) and all(n in self.poses for n in image_names)

    def has_all_intrinsics(self, image_names: list[str]) -> bool:
        return bool(image_names) and all(self.intrinsics_for(n) is not None for n in image_names)


def _parse_intrinsics(raw: Any, where: str) -> Intrinsics:
    try:
        return Intrinsics(
            str(raw["model"]),
            int(raw["width"]),
            int(raw["height"]),
            tuple(float(v) for v in raw["params"]),
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"cameras.json {where}: bad intrinsics ({exc})") from exc


def parse_cameras(raw: dict[str, Any]) -> CamerasSpec:
    """Parse the cameras.json document; raises InputError on malformed content."""
    if not isinstance(raw, dict):
        raise InputError("cameras.json must be a JSON object")
    shared = _parse_intrinsics(raw["intrinsics"], "intrinsics") if "intrinsics" in raw else None
    per_image = {
        str(name): _parse_intrinsics(v, f"intrinsics_per_image[{name}]")
        for name, v in dict(raw.get("intrinsics_per_image", {})).items()
    }
    poses: dict[str, Mat4] = {}
    for name, m in dict(raw.get("poses", {})).items():
        try:
            pose = as_mat4(m, f"poses[{name}]")
        except ShapeError as exc:
            raise InputError(f"cameras.json: {exc.detail}") from exc
        if abs(np.linalg.det(pose[:3, :3]) - 1.0) > 1e-3:
            raise InputError(f"cameras.json poses[{name}] is not a rigid transform")
        poses[str(name)] = pose
    return CamerasSpec(shared, per_image, poses)


def load_cameras(path: Path) -> CamerasSpec:
    """Read and parse a cameras.json file; raises InputError when unreadable."""
    try:
        raw = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise InputError(f"cannot read cameras file {path}: {exc}") from exc
    return parse_cameras(raw)


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

    def to_json(self) -> dict[str, Any]:
        """The cameras.json entry of this view: K, dist, size, env_from_cam, model."""
        return {
            "K": self.intrinsics.k_matrix.tolist(),
            "dist": self.intrinsics.dist_coeffs.tolist(),
            "width": self.intrinsics.width,
            "height": self.intrinsics.height,
            "intrinsics": self.intrinsics.to_json(),
            "env_from_cam": self.env_from_cam.tolist(),
        }
