"""Write one scenario to disk: images, YOLO labels, cameras, reference, ground truth, models.

Layout under ``out_dir``::

    before/images/view_000.png   before/labels/view_000.txt   before/classes.txt
    before/cameras.json          after/... (same)             reference.json
    ground_truth.json            objects/<class>.ply

``ground_truth.json``: ``scenario``, ``seed``, ``classes`` (as classes.txt), ``objects``
({class: {"model": "objects/<class>.ply", "symmetry": spec or null}}, the library's format),
``room`` (RoomOptions, enough to rebuild the room meshes), ``reference`` (as
reference.json), ``before`` / ``after`` ([{"instance_id", "object", "class_id",
"env_from_object", "support"}]), ``changes`` ([{"type", "object", "instance_id", "pose",
"previous_pose", "replaced_object", "replaced_instance_id"}], docs/contract.md field meanings)
and ``camera_poses`` ({capture: {image name: env_from_cam}}). Poses are 4×4 row-major
lists, metres; cameras have OpenCV axes and pixel centres at integer coordinates.

A scene that uses any option beyond the original generator's (a room layout, texture
variant or shelf, camera rings, camera effects, distractors, a target) also gets
``supports`` ([{"name", "centre_m", "size_m", "z_m"}], every surface objects stand on),
``camera`` (the true intrinsics, cameras.json's form, lens included), ``effects``
(EffectsOptions) and ``distractors`` ({name: {"model": "distractors/<name>.ply"}}); a
distractor's placement has ``class_id`` None and ``distractor`` true, its change ``object``
None and ``unidentified`` true. Scenes without them are written byte for byte as before.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from app.formats.cameras import CamerasFile, Pose, pose_rows, write_cameras
from app.formats.yolo import YoloBox, yolo_line
from workers.pipeline.errors import InputError, ShapeError
from workers.pipeline.geometry import Mat4, as_mat4
from workers.pipeline.synth.cameras import (
    camera_path,
    cameras_json_intrinsics,
    distortion_coeffs,
    intrinsics_matrix,
)
from workers.pipeline.synth.options import (
    PRESETS,
    DetectionOptions,
    RoomOptions,
    SynthOptions,
)
from workers.pipeline.synth.render import RenderedView, Renderer, ViewEffects, motion_blur_kernel
from workers.pipeline.synth.scene import Placement, Scenario, build_scenario, room_surfaces
from workers.pipeline.synth.shapes import Mesh, ObjectModel, builtin_models, write_model_ply

CAPTURES: tuple[str, str] = ("before", "after")
Progress = Callable[[str, float], None]


@dataclass(frozen=True)
class Detection:
    """One YOLO box: ``class_id``, pixel-edge box (x0, y0, x1, y1), confidence in (0, 1],
    and the placement index it came from (−1 for a false positive)."""

    class_id: int
    box_px: tuple[float, float, float, float]
    confidence: float
    instance: int


def visible_boxes(
    instance: NDArray[np.int32], min_pixels: int
) -> dict[int, tuple[int, int, int, int, int]]:
    """Per visible instance index: (x0, y0, x1, y1, n_pixels) with exclusive x1, y1, from an
    (H, W) instance buffer; instances with fewer than ``min_pixels`` pixels are left out."""
    if instance.ndim != 2:
        raise ShapeError(f"instance buffer must be (H, W), got {instance.shape}")
    out = {}
    for idx in np.unique(instance[instance >= 0]):
        rows, cols = np.nonzero(instance == idx)
        if len(rows) >= min_pixels:
            out[int(idx)] = (
                int(cols.min()),
                int(rows.min()),
                int(cols.max()) + 1,
                int(rows.max()) + 1,
                len(rows),
            )
    return out


def detect(
    instance: NDArray[np.int32],
    class_ids: Sequence[int],
    n_classes: int,
    options: DetectionOptions,
    rng: np.random.Generator,
) -> list[Detection]:
    """Detections of one view from its instance buffer; ``class_ids[i]`` is the class of
    placement i (−1: not a library object, never detected). Applies box jitter (pixels),
    missed detections and false positives."""
    h, w = instance.shape
    out = []
    for idx, (x0, y0, x1, y1, n) in visible_boxes(instance, options.min_visible_px).items():
        if class_ids[idx] < 0:
            continue
        if options.miss_rate > 0 and rng.uniform() < options.miss_rate:
            continue
        edges = np.asarray([x0, y0, x1, y1], np.float64)
        if options.box_jitter_px > 0:
            edges += rng.normal(0.0, options.box_jitter_px, 4)
            edges = np.clip(edges, 0, [w, h, w, h])
            if edges[2] - edges[0] < 2 or edges[3] - edges[1] < 2:
                continue
        box = (float(edges[0]), float(edges[1]), float(edges[2]), float(edges[3]))
        confidence = float(
            np.clip(0.55 + 0.4 * min(1.0, n / 4000.0) + rng.normal(0, 0.03), 0.05, 0.99)
        )
        out.append(Detection(class_ids[idx], box, confidence, idx))
    if options.false_positive_rate > 0 and rng.uniform() < options.false_positive_rate:
        size = rng.uniform(0.05, 0.25, 2) * [w, h]
        corner = rng.uniform(0, 1, 2) * ([w, h] - size)
        fp = (
            float(corner[0]),
            float(corner[1]),
            float(corner[0] + size[0]),
            float(corner[1] + size[1]),
        )
        out.append(Detection(int(rng.integers(n_classes)), fp, float(rng.uniform(0.3, 0.6)), -1))
    return out


def yolo_lines(detections: Sequence[Detection], width: int, height: int, confidence: bool) -> str:
    """YOLO text (:mod:`app.formats.yolo`): ``<class> <cx> <cy> <w> <h> [<conf>]``
    normalised to the image size."""
    lines = []
    for det in detections:
        x0, y0, x1, y1 = det.box_px
        box = YoloBox(
            class_id=int(det.class_id),
            cx=(x0 + x1) / 2 / width,
            cy=(y0 + y1) / 2 / height,
            w=(x1 - x0) / width,
            h=(y1 - y0) / height,
            confidence=float(det.confidence) if confidence else None,
        )
        lines.append(yolo_line(box))
    return "".join(line + "\n" for line in lines)


def view_name(index: int, options: SynthOptions) -> str:
    """Image file name of view ``index``."""
    ext = "png" if options.look.jpeg_quality is None else "jpg"
    return f"view_{index:03d}.{ext}"


def capture_path(scenario: Scenario, capture: str, options: SynthOptions) -> list[Mat4]:
    """True ``env_from_cam`` (4×4, OpenCV axes) of every view of ``capture``, in view order."""
    scenario.capture(capture)  # validates the name
    rng = np.random.default_rng([scenario.seed, 2, CAPTURES.index(capture)])
    return camera_path(options.path, rng)


def view_effects(options: SynthOptions, seed: int, capture: str, index: int) -> ViewEffects | None:
    """The camera effects of view ``index`` of ``capture`` (None when no effect is on):
    the capture's gain × white balance × exp(N(0, exposure_jitter)), and a motion blur of
    U(0, motion_blur_px) pixels in a uniform direction, drawn from (seed, 5, capture, view)."""
    fx = options.effects
    if not fx.active:
        return None
    c = CAPTURES.index(capture)
    rng = np.random.default_rng([seed, 5, c, index])
    gain = fx.capture_gain[c] * np.asarray(fx.capture_white_balance[c], np.float64)
    gain = gain * float(np.exp(fx.exposure_jitter * rng.standard_normal()))
    kernel = None
    if fx.motion_blur_px > 0:
        length, angle = rng.uniform(0.0, fx.motion_blur_px), rng.uniform(0.0, np.pi)
        kernel = motion_blur_kernel(float(length), float(angle))
    return ViewEffects(gain.astype(np.float32), kernel)


def render_capture(
    scenario: Scenario, capture: str, options: SynthOptions
) -> Iterator[tuple[str, RenderedView]]:
    """Render every view of ``capture`` ("before" or "after") as (image name, view)."""
    placements = scenario.capture(capture)
    c = CAPTURES.index(capture)
    k = intrinsics_matrix(options.camera)
    renderer = Renderer(
        scenario.room,
        placements,
        scenario.markers,
        options.camera,
        options.look,
        k,
        distortion_coeffs(options.effects),
    )
    path = camera_path(options.path, np.random.default_rng([scenario.seed, 2, c]))
    for index, env_from_cam in enumerate(path):
        rng = np.random.default_rng([scenario.seed, 3, c, index])
        effects = view_effects(options, scenario.seed, capture, index)
        yield view_name(index, options), renderer.render(env_from_cam, rng, effects)


def _encode(image_rgb: NDArray[np.uint8], quality: int | None) -> bytes:
    bgr = cv2.cvtColor(image_rgb, cv2.COLOR_RGB2BGR)
    if quality is None:
        ok, buf = cv2.imencode(".png", bgr, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    else:
        ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise InputError("image encoding failed")
    return bytes(buf.tobytes())


def write_capture(
    scenario: Scenario,
    capture: str,
    options: SynthOptions,
    out_dir: Path,
    progress: Progress | None = None,
) -> None:
    """Write ``out_dir/<capture>/``: images, labels, classes.txt and cameras.json."""
    root = out_dir / capture
    (root / "images").mkdir(parents=True, exist_ok=True)
    (root / "labels").mkdir(parents=True, exist_ok=True)
    classes = [m.name for m in scenario.models]
    (root / "classes.txt").write_text("".join(name + "\n" for name in classes))
    class_ids = [
        classes.index(p.model.name) if p.model.name in classes else -1
        for p in scenario.capture(capture)
    ]
    c = CAPTURES.index(capture)
    poses: dict[str, Pose] = {}
    for index, (name, view) in enumerate(render_capture(scenario, capture, options)):
        (root / "images" / name).write_bytes(_encode(view.image, options.look.jpeg_quality))
        rng = np.random.default_rng([scenario.seed, 4, c, index])
        dets = detect(view.instance, class_ids, len(classes), options.detection, rng)
        text = yolo_lines(
            dets, options.camera.width, options.camera.height, options.detection.confidence
        )
        (root / "labels" / (Path(name).stem + ".txt")).write_text(text)
        poses[name] = pose_rows(view.env_from_cam.tolist())
        if progress is not None:
            progress(f"render_{capture}", (index + 1) / options.path.n_views)
    _write_cameras(root / "cameras.json", options, poses)
    _remove_stale(root / "images", set(poses))
    _remove_stale(root / "labels", {Path(name).stem + ".txt" for name in poses})


def _write_cameras(path: Path, options: SynthOptions, poses: dict[str, Pose]) -> None:
    """cameras.json: the declared intrinsics (lens included) and, with ``write_poses``, the
    true poses. Without declared intrinsics and poses no file is written (an old one is
    removed); InputError for poses without intrinsics, which cameras.json cannot hold."""
    if not options.effects.declare_intrinsics:
        _check_cameras_options(options)
        path.unlink(missing_ok=True)
        return
    cameras = CamerasFile(
        intrinsics=cameras_json_intrinsics(options.camera, options.effects),
        poses=poses if options.write_poses else {},
    )
    write_cameras(path, cameras)


def _check_cameras_options(options: SynthOptions) -> None:
    """InputError when cameras.json cannot be written as asked: poses without declared
    intrinsics, or an unknown lens model."""
    distortion_coeffs(options.effects)
    if options.write_poses and not options.effects.declare_intrinsics:
        raise InputError("write_poses needs declared intrinsics (effects.declare_intrinsics)")


def _remove_stale(folder: Path, keep: set[str]) -> None:
    """Delete files of an earlier run in ``folder`` that this run did not write."""
    for path in folder.iterdir():
        if path.is_file() and path.name not in keep:
            path.unlink()


def ground_truth(scenario: Scenario, options: SynthOptions) -> dict[str, Any]:
    """The ground-truth document: classes, models, room, placements of both captures, changes.

    Poses are ``env_from_object`` 4×4 row-major lists (metres); ``symmetry`` (object frame)
    is None or {"kind": "continuous", "axis", "origin"}: the library's symmetry format
    (``workers.pipeline.model.symmetry_group.spec_from_json`` reads it).
    """
    classes = [m.name for m in scenario.models]

    def item(p: Placement) -> dict[str, Any]:
        out: dict[str, Any] = {
            "instance_id": p.instance_id,
            "object": p.model.name,
            "class_id": classes.index(p.model.name) if p.model.name in classes else None,
            "env_from_object": p.env_from_object.tolist(),
            "support": p.support,
        }
        if p.model.name not in classes:
            out["distractor"] = True
        return out

    def capture(name: str) -> list[dict[str, Any]]:
        return [item(p) for p in scenario.capture(name)]

    doc = {
        "format": "twindelta-synth/1",
        "scenario": scenario.name,
        "seed": scenario.seed,
        "classes": classes,
        "objects": {
            m.name: {"model": f"objects/{m.name}.ply", "symmetry": m.symmetry}
            for m in scenario.models
        },
        "room": _room_json(options.room),
        "reference": scenario.markers.reference(),
        "before": capture("before"),
        "after": capture("after"),
        "changes": list(scenario.changes),
        "camera_poses": {
            name: {
                view_name(i, options): pose.tolist()
                for i, pose in enumerate(capture_path(scenario, name, options))
            }
            for name in CAPTURES
        },
    }
    if _extended(options):
        doc["supports"] = [s.to_json() for s in scenario.supports]
        doc["camera"] = cameras_json_intrinsics(options.camera, options.effects).to_json()
        doc["effects"] = asdict(options.effects)
        doc["distractors"] = {
            m.name: {"model": f"distractors/{m.name}.ply"} for m in scenario.distractors
        }
    return doc


#: RoomOptions fields added after the first generator: written only when not at default.
_NEW_ROOM_FIELDS = ("layout", "texture_variant", "shelf", "shelf_size_m", "shelf_centre_m")


def _room_json(room: RoomOptions) -> dict[str, Any]:
    """``room`` as written in ground_truth.json (new fields only where not at default)."""
    default = RoomOptions()
    return {
        k: v
        for k, v in asdict(room).items()
        if k not in _NEW_ROOM_FIELDS or v != getattr(default, k)
    }


def _extended(options: SynthOptions) -> bool:
    """Whether the scene uses an option beyond the original generator's."""
    room = options.room
    return bool(
        options.effects.active
        or options.distractors
        or options.target is not None
        or options.path.rings_m
        or any(getattr(room, k) != getattr(RoomOptions(), k) for k in _NEW_ROOM_FIELDS)
    )


def generate(
    out_dir: Path,
    scenario: str,
    seed: int = 0,
    options: SynthOptions = PRESETS["demo"],
    models: Sequence[ObjectModel] | None = None,
    progress: Progress | None = None,
) -> Scenario:
    """Generate and write scenario ``scenario`` under ``out_dir``; returns the scene.

    ``models`` defaults to the built-in shapes. Same arguments ⇒ byte-identical files.
    """
    _check_cameras_options(options)
    built = build_scenario(scenario, models or builtin_models(), seed, options)
    out_dir.mkdir(parents=True, exist_ok=True)
    for model in built.models:
        write_model_ply(model, out_dir / "objects" / f"{model.name}.ply")
    for model in built.distractors:
        write_model_ply(model, out_dir / "distractors" / f"{model.name}.ply")
    (out_dir / "reference.json").write_text(json.dumps(built.markers.reference(), indent=1))
    (out_dir / "ground_truth.json").write_text(json.dumps(ground_truth(built, options), indent=1))
    for capture in CAPTURES:
        write_capture(built, capture, options, out_dir, progress)
    return built


def _legacy(mesh: Mesh, env_from_mesh: NDArray[np.float64]) -> o3d.geometry.TriangleMesh:
    verts = mesh.vertices @ env_from_mesh[:3, :3].T + env_from_mesh[:3, 3]
    return o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(verts), o3d.utility.Vector3iVector(mesh.triangles)
    )


def true_surfaces(scenario: Scenario, capture: str) -> dict[str, o3d.geometry.TriangleMesh]:
    """Every true surface of ``capture`` as legacy meshes in the environment frame (metres):
    room parts by name ("floor", "wall_0".., "table") and objects by instance id."""
    out = {s.name: _legacy(s.mesh, np.eye(4)) for s in scenario.room}
    for p in scenario.capture(capture):
        out[p.instance_id] = _legacy(p.model.mesh, p.env_from_object)
    return out


def load_true_surfaces(scenario_dir: Path, capture: str) -> dict[str, o3d.geometry.TriangleMesh]:
    """:func:`true_surfaces` rebuilt from a written scenario (ground_truth.json + objects/)."""
    path = scenario_dir / "ground_truth.json"
    if not path.is_file():
        raise InputError(f"no ground_truth.json in {scenario_dir}")
    if capture not in CAPTURES:
        raise InputError(f"capture must be 'before' or 'after', got {capture!r}")
    gt = json.loads(path.read_text())
    fields: dict[str, Any] = {
        k: tuple(v) if isinstance(v, list) else v for k, v in gt["room"].items()
    }
    room = RoomOptions(**fields)
    out = {s.name: _legacy(s.mesh, np.eye(4)) for s in room_surfaces(room)}
    files = {**gt.get("distractors", {}), **gt["objects"]}
    for item in gt[capture]:
        model = o3d.io.read_triangle_mesh(scenario_dir / files[item["object"]]["model"])
        mesh = Mesh(np.asarray(model.vertices), np.asarray(model.triangles, np.int32))
        out[item["instance_id"]] = _legacy(
            mesh, as_mat4(item["env_from_object"], "env_from_object")
        )
    return out
