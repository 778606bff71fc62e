"""cameras.json: the one reader and writer, used by the upload API and every pipeline stage.

The format (a capture station's upload, and what ``reconstruct`` writes for the next stage)::

    {"intrinsics": {"model": "PINHOLE", "width": 640, "height": 480,
                    "params": [fx, fy, cx, cy]},             # shared by every image, or
     "intrinsics_per_image": {"a.jpg": {...}},               # per image (overrides shared)
     "poses": {"a.jpg": [[...4...], [...], [...], [0, 0, 0, 1]]}}  # optional env_from_cam

At least one of ``intrinsics`` and ``intrinsics_per_image`` is given. Params follow OpenCV's
pixel convention (the centre of the top-left pixel is (0, 0)); models are COLMAP's names,
limited to those every stage can use (:data:`CAMERA_MODELS`). ``poses`` are 4×4 rigid
``env_from_cam`` transforms, metres, OpenCV camera axes (x right, y down, z forward).

Everything here is the standard library only: the API and the pipeline both import it.
:func:`read_cameras` takes an already-parsed document (the API parses it with its strict
loader); :func:`load_cameras_file` reads a file. Errors are :class:`FormatError` with
code ``InvalidCameras``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from app.formats.errors import FormatError, show

CODE = "InvalidCameras"
KEYS = ("intrinsics", "intrinsics_per_image", "poses")
MAX_IMAGE_SIDE = 1_000_000  # pixels: far past any camera, and safe as a 32-bit int
PARAM_LIMIT = 2**63  # |param| must be below it (the API's 64-bit number bound)
LAST_ROW_ATOL = 1e-6  # |last row − [0, 0, 0, 1]| allowed in a pose
ROTATION_ATOL = 1e-4  # |RᵀR − I| allowed in a pose's 3×3 block


@dataclass(frozen=True)
class CameraModel:
    """A COLMAP camera model the stages can use: its parameter names, in order."""

    name: str
    params: tuple[str, ...]

    @property
    def n_params(self) -> int:
        return len(self.params)

    @property
    def principal_point(self) -> tuple[int, int]:
        """Indices of cx and cy in the params."""
        return self.params.index("cx"), self.params.index("cy")


#: Models every stage can use: reconstruct feeds them to COLMAP and undistorts with OpenCV
#: (k1, k2, p1, p2); compare and pose take the pinhole part of images already undistorted.
CAMERA_MODELS: dict[str, CameraModel] = {
    m.name: m
    for m in (
        CameraModel("SIMPLE_PINHOLE", ("f", "cx", "cy")),
        CameraModel("PINHOLE", ("fx", "fy", "cx", "cy")),
        CameraModel("SIMPLE_RADIAL", ("f", "cx", "cy", "k1")),
        CameraModel("RADIAL", ("f", "cx", "cy", "k1", "k2")),
        CameraModel("OPENCV", ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")),
    )
}

Pose = tuple[tuple[float, float, float, float], ...]
"""A 4×4 matrix as four rows of four floats."""


def pose_rows(matrix: Sequence[Sequence[float]]) -> Pose:
    """A 4×4 matrix (nested sequences, e.g. ``ndarray.tolist()``) as a :data:`Pose`, values
    as they are (not checked: :func:`check_rigid` checks)."""
    return tuple((float(r[0]), float(r[1]), float(r[2]), float(r[3])) for r in matrix)


@dataclass(frozen=True)
class Camera:
    """One camera's intrinsics: COLMAP model name, image size in pixels, params (OpenCV
    pixel convention). Raises :class:`FormatError` when the model is not one of
    :data:`CAMERA_MODELS`, the params do not fit it, or the size is not positive."""

    model: str
    width: int
    height: int
    params: tuple[float, ...]

    def __post_init__(self) -> None:
        check_camera(self.to_json(), "camera")

    @property
    def pinhole(self) -> tuple[float, float, float, float]:
        """(fx, fy, cx, cy) in pixels: the pinhole part of the params (fx = fy = f for the
        SIMPLE_ models and RADIAL)."""
        p = CAMERA_MODELS[self.model].params
        named = dict(zip(p, self.params, strict=True))
        if "f" in named:
            return named["f"], named["f"], named["cx"], named["cy"]
        return named["fx"], named["fy"], named["cx"], named["cy"]

    @property
    def distortion(self) -> tuple[float, float, float, float, float]:
        """OpenCV's (k1, k2, p1, p2, k3); zeros where the model has none."""
        named = dict(zip(CAMERA_MODELS[self.model].params, self.params, strict=True))
        k1, k2, p1, p2 = (named.get(k, 0.0) for k in ("k1", "k2", "p1", "p2"))
        return k1, k2, p1, p2, 0.0

    def to_json(self) -> dict[str, Any]:
        return {
            "model": self.model,
            "width": self.width,
            "height": self.height,
            "params": list(self.params),
        }


@dataclass(frozen=True)
class CamerasFile:
    """A parsed cameras.json: shared and per-image intrinsics, and ``env_from_cam`` poses
    (4×4 rigid, metres, OpenCV axes) by image name."""

    intrinsics: Camera | None = None
    intrinsics_per_image: Mapping[str, Camera] = field(default_factory=dict)
    poses: Mapping[str, Pose] = field(default_factory=dict)

    def camera_for(self, image_name: str) -> Camera | None:
        """The intrinsics of one image, or None when the file does not give them."""
        return self.intrinsics_per_image.get(image_name, self.intrinsics)

    def to_json(self) -> dict[str, Any]:
        """The document :func:`read_cameras` reads back to an equal value."""
        out: dict[str, Any] = {}
        if self.intrinsics is not None:
            out["intrinsics"] = self.intrinsics.to_json()
        if self.intrinsics_per_image:
            out["intrinsics_per_image"] = {
                name: cam.to_json() for name, cam in self.intrinsics_per_image.items()
            }
        if self.poses:
            out["poses"] = {name: [list(row) for row in m] for name, m in self.poses.items()}
        return out


# --- reading ---------------------------------------------------------------------------------


def read_cameras(
    doc: Any, where: str = "cameras.json", image_names: Collection[str] | None = None
) -> CamerasFile:
    """Check a parsed cameras.json document and return it typed.

    ``where`` names the document in errors; with ``image_names``, every image the document
    names must be one of them. Raises :class:`FormatError` (code ``InvalidCameras``) naming
    the field: unknown keys, a model outside :data:`CAMERA_MODELS`, params of the wrong
    count or not finite, a size that is not a positive integer up to
    :data:`MAX_IMAGE_SIDE`, a pose that is not a 4×4 rigid transform.
    """
    if not isinstance(doc, dict):
        raise FormatError(where, "expected a JSON object", code=CODE)
    unknown = sorted(set(doc) - set(KEYS))
    if unknown:
        raise FormatError(where, f"unknown keys {unknown}", code=CODE)
    if "intrinsics" not in doc and "intrinsics_per_image" not in doc:
        raise FormatError(where, "give 'intrinsics' or 'intrinsics_per_image'", code=CODE)
    shared = None
    if "intrinsics" in doc:
        shared = _camera(check_camera(doc["intrinsics"], f"{where}: intrinsics"))
    per_image: dict[str, Camera] = {}
    if "intrinsics_per_image" in doc:
        named = _named_map(doc["intrinsics_per_image"], where, "intrinsics_per_image")
        per_image = {
            name: _camera(check_camera(value, f"{where}: intrinsics_per_image[{name!r}]"))
            for name, value in named.items()
        }
        _check_names(named, image_names, where, "intrinsics_per_image")
    poses: dict[str, Pose] = {}
    if "poses" in doc:
        named = _named_map(doc["poses"], where, "poses")
        _check_names(named, image_names, where, "poses")
        poses = {name: check_rigid(m, f"{where}: poses[{name!r}]") for name, m in named.items()}
    return CamerasFile(shared, per_image, poses)


def load_cameras_file(path: Path, image_names: Collection[str] | None = None) -> CamerasFile:
    """Read a cameras.json file; :class:`FormatError` when it is unreadable, not JSON
    (NaN and Infinity included) or not the format."""
    where = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise FormatError(where, f"cannot read ({exc})", code=CODE) from exc
    try:
        doc = json.loads(text, parse_constant=_no_constant)
    except ValueError as exc:
        raise FormatError(where, f"not JSON ({exc})", code=CODE) from exc
    except RecursionError as exc:
        raise FormatError(where, "nested too deep", code=CODE) from exc
    return read_cameras(doc, where, image_names)


def _no_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a JSON number")


def _camera(checked: dict[str, Any]) -> Camera:
    return Camera(checked["model"], checked["width"], checked["height"], tuple(checked["params"]))


def _named_map(value: Any, where: str, key: str) -> dict[str, Any]:
    if not isinstance(value, dict) or not value:
        raise FormatError(where, f"{key} must be a non-empty object by image name", code=CODE)
    return value


def _check_names(
    named: dict[str, Any], image_names: Collection[str] | None, where: str, key: str
) -> None:
    if image_names is None:
        return
    missing = sorted(set(named) - set(image_names))
    if missing:
        raise FormatError(
            where, f"{key} names images that were not uploaded: {missing[:5]}", code=CODE
        )


def _is_number(value: Any) -> bool:
    return (
        isinstance(value, int | float)
        and not isinstance(value, bool)
        and abs(value) < PARAM_LIMIT
        and math.isfinite(value)
    )


def check_camera(value: Any, where: str) -> dict[str, Any]:
    """One intrinsics object ``{model, width, height, params}`` checked and normalised
    (params as floats); :class:`FormatError` naming ``where`` otherwise."""
    if not isinstance(value, dict):
        raise FormatError(where, "expected {model, width, height, params}", code=CODE)
    model = value.get("model")
    if not isinstance(model, str) or model not in CAMERA_MODELS:
        raise FormatError(
            where, f"model {show(model)} is not one of {sorted(CAMERA_MODELS)}", code=CODE
        )
    size = []
    for key in ("width", "height"):
        dim = value.get(key)
        if not isinstance(dim, int) or isinstance(dim, bool) or not 0 < dim <= MAX_IMAGE_SIDE:
            raise FormatError(
                where, f"{key} must be a positive integer (at most {MAX_IMAGE_SIDE})", code=CODE
            )
        size.append(dim)
    params = value.get("params")
    expected = CAMERA_MODELS[model].n_params
    if not isinstance(params, list | tuple) or len(params) != expected:
        raise FormatError(
            where, f"model {model} takes {expected} params, got {show(params)}", code=CODE
        )
    if not all(_is_number(p) for p in params):
        raise FormatError(where, "params must be finite numbers", code=CODE)
    return {
        "model": model,
        "width": size[0],
        "height": size[1],
        "params": [float(p) for p in params],
    }


def check_rigid(matrix: Any, where: str, *, code: str = CODE) -> Pose:
    """A 4×4 rigid transform (last row [0, 0, 0, 1] within :data:`LAST_ROW_ATOL`, a 3×3
    block with RᵀR = I within :data:`ROTATION_ATOL` and a positive determinant) as rows of
    floats; :class:`FormatError` naming ``where`` otherwise."""
    if not (
        isinstance(matrix, list | tuple)
        and len(matrix) == 4
        and all(isinstance(row, list | tuple) and len(row) == 4 for row in matrix)
        and all(_is_number(v) for row in matrix for v in row)
    ):
        raise FormatError(where, "expected a 4×4 matrix of finite numbers", code=code)
    m = [[float(v) for v in row] for row in matrix]
    if not all(_close(m[3][j], float(j == 3), LAST_ROW_ATOL) for j in range(4)):
        raise FormatError(where, "last row must be [0, 0, 0, 1]", code=code)
    r = [row[:3] for row in m[:3]]
    orthonormal = all(
        _close(sum(r[k][i] * r[k][j] for k in range(3)), float(i == j), ROTATION_ATOL)
        for i in range(3)
        for j in range(3)
    )
    if not orthonormal or _det3(r) < 0:
        raise FormatError(where, "the 3×3 block is not a rotation (orthonormal, det +1)", code=code)
    return tuple((row[0], row[1], row[2], row[3]) for row in m)


def _close(value: float, target: float, atol: float) -> bool:
    """numpy.isclose's test: |value − target| ≤ atol + 1e-5·|target|."""
    return abs(value - target) <= atol + 1e-5 * abs(target)


def _det3(r: list[list[float]]) -> float:
    return (
        r[0][0] * (r[1][1] * r[2][2] - r[1][2] * r[2][1])
        - r[0][1] * (r[1][0] * r[2][2] - r[1][2] * r[2][0])
        + r[0][2] * (r[1][0] * r[2][1] - r[1][1] * r[2][0])
    )


# --- writing ---------------------------------------------------------------------------------


def write_cameras(path: Path, cameras: CamerasFile) -> None:
    """Write ``cameras`` as cameras.json (indented one space)."""
    Path(path).write_text(json.dumps(cameras.to_json(), indent=1))


# --- the published JSON Schema ----------------------------------------------------------------


def cameras_schema() -> dict[str, Any]:
    """The JSON Schema (draft 2020-12) of cameras.json, generated from :data:`CAMERA_MODELS`
    and the limits above; published as ``openapi/cameras.schema.json`` for capture-station
    authors. What it cannot say (a pose is rigid, names match the uploaded images) the
    reader checks."""
    number = {"type": "number"}
    models = [
        {
            "properties": {
                "model": {"const": m.name},
                "params": {
                    "type": "array",
                    "items": number,
                    "minItems": m.n_params,
                    "maxItems": m.n_params,
                    "description": ", ".join(m.params),
                },
            }
        }
        for m in CAMERA_MODELS.values()
    ]
    side = {"type": "integer", "minimum": 1, "maximum": MAX_IMAGE_SIDE}
    intrinsics = {
        "type": "object",
        "description": "COLMAP model, image size in pixels, params in OpenCV's pixel "
        "convention (the centre of the top-left pixel is (0, 0))",
        "required": ["model", "width", "height", "params"],
        "properties": {
            "model": {"enum": list(CAMERA_MODELS)},
            "width": side,
            "height": side,
            "params": {"type": "array", "items": number},
        },
        "oneOf": models,
    }
    row = {"type": "array", "items": number, "minItems": 4, "maxItems": 4}
    pose = {
        "type": "array",
        "description": "env_from_cam: 4×4 rigid transform, metres, OpenCV camera axes",
        "items": row,
        "minItems": 4,
        "maxItems": 4,
    }
    by_image = {"type": "object", "minProperties": 1}
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": "cameras.json",
        "description": "Camera intrinsics and optional env_from_cam poses of a capture, "
        "by image file name.",
        "type": "object",
        "additionalProperties": False,
        "anyOf": [{"required": ["intrinsics"]}, {"required": ["intrinsics_per_image"]}],
        "properties": {
            "intrinsics": {"$ref": "#/$defs/intrinsics"},
            "intrinsics_per_image": {
                **by_image,
                "additionalProperties": {"$ref": "#/$defs/intrinsics"},
            },
            "poses": {**by_image, "additionalProperties": {"$ref": "#/$defs/pose"}},
        },
        "$defs": {"intrinsics": intrinsics, "pose": pose},
    }


def schema_text() -> str:
    """:func:`cameras_schema` as the file ``openapi/cameras.schema.json`` holds it."""
    return json.dumps(cameras_schema(), indent=2, ensure_ascii=False) + "\n"


# --- an earlier reconstruct output -------------------------------------------------------------


def from_reconstruction_images(doc: Any, where: str = "cameras.json") -> CamerasFile:
    """Read the cameras.json that ``reconstruct`` wrote before it wrote this format,
    ``{"images": {name: {"intrinsics": {...}, "env_from_cam": 4×4, "K", "dist", ...}}}``,
    as stored for older snapshots; :class:`FormatError` when it is not that either."""
    if not isinstance(doc, dict) or set(doc) != {"images"} or not isinstance(doc["images"], dict):
        raise FormatError(where, 'expected {"images": {name: view}}', code=CODE)
    per_image: dict[str, Camera] = {}
    poses: dict[str, Pose] = {}
    for name, view in doc["images"].items():
        at = f"{where}: images[{name!r}]"
        if not isinstance(view, dict):
            raise FormatError(at, "expected {intrinsics, env_from_cam}", code=CODE)
        per_image[name] = _camera(check_camera(view.get("intrinsics"), f"{at}.intrinsics"))
        poses[name] = check_rigid(view.get("env_from_cam"), f"{at}.env_from_cam")
    return CamerasFile(None, per_image, poses)


def is_reconstruction_images(doc: Any) -> bool:
    """Whether ``doc`` is the earlier reconstruct output (see
    :func:`from_reconstruction_images`)."""
    return isinstance(doc, dict) and set(doc) == {"images"}


if __name__ == "__main__":  # python -m app.formats.cameras > openapi/cameras.schema.json
    print(schema_text(), end="")
