"""Options of the scene generator: frozen dataclasses and named presets.

Every length is in metres, every angle in degrees, image sizes in pixels.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from workers.pipeline.errors import InputError

SCENARIOS: tuple[str, ...] = (
    "added",
    "removed",
    "moved",
    "swapped",
    "symmetric_moved",
    "multiple",
    "no_change",
)


@dataclass(frozen=True)
class CameraOptions:
    """Pinhole intrinsics (OpenCV convention: pixel centres at integer coordinates)."""

    width: int = 800
    height: int = 600
    focal_px: float = 650.0


@dataclass(frozen=True)
class PathOptions:
    """Camera path: ``n_views`` on a jittered ring around the scene, looking at its centre."""

    n_views: int = 30
    radius_m: float = 1.6
    radius_jitter_m: float = 0.2
    height_min_m: float = 0.8
    height_max_m: float = 1.6
    height_waves: float = 2.0
    target_jitter_m: float = 0.12
    arc_deg: float = 360.0


@dataclass(frozen=True)
class RoomOptions:
    """Room, reference markers and the optional table."""

    size_m: float = 6.0
    wall_height_m: float = 2.6
    marker_ids: tuple[int, ...] = (0, 1, 2, 3, 4, 5, 6, 7)
    marker_size_m: float = 0.15
    marker_ring_m: float = 0.85
    marker_margin_m: float = 0.025
    table: bool = False
    table_size_m: tuple[float, float, float] = (0.8, 0.45, 0.42)
    table_centre_m: tuple[float, float] = (0.0, -1.2)
    placement_radius_m: float = 0.75


@dataclass(frozen=True)
class LookOptions:
    """Shading (Lambertian + ambient), sensor noise and file encoding."""

    light_dir: tuple[float, float, float] = (0.4, 0.25, 1.0)
    ambient: float = 0.35
    diffuse: float = 0.75
    noise_sigma: float = 0.0
    jpeg_quality: int | None = None
    marker_supersample: int = 4


@dataclass(frozen=True)
class DetectionOptions:
    """How YOLO boxes are derived from visible pixels, and how they are corrupted."""

    min_visible_px: int = 150
    box_jitter_px: float = 0.0
    miss_rate: float = 0.0
    false_positive_rate: float = 0.0
    confidence: bool = True


@dataclass(frozen=True)
class SynthOptions:
    """Everything one scenario needs besides the scenario name, the objects and the seed."""

    camera: CameraOptions = field(default_factory=CameraOptions)
    path: PathOptions = field(default_factory=PathOptions)
    room: RoomOptions = field(default_factory=RoomOptions)
    look: LookOptions = field(default_factory=LookOptions)
    detection: DetectionOptions = field(default_factory=DetectionOptions)
    write_poses: bool = True  # true poses in cameras.json (ground_truth.json always has them)
    move_min_m: float = 0.2


PRESETS: dict[str, SynthOptions] = {
    "demo": SynthOptions(
        path=PathOptions(n_views=30),
        look=LookOptions(noise_sigma=1.5, jpeg_quality=92),
        write_poses=False,
    ),
    "bench": SynthOptions(
        write_poses=False,
        path=PathOptions(n_views=40),
        look=LookOptions(noise_sigma=2.0),
        detection=DetectionOptions(box_jitter_px=2.0, miss_rate=0.05, false_positive_rate=0.02),
    ),
    "tiny": SynthOptions(
        camera=CameraOptions(width=320, height=240, focal_px=260.0),
        path=PathOptions(n_views=6),
        detection=DetectionOptions(min_visible_px=40),
    ),
}


def preset(name: str, **overrides: object) -> SynthOptions:
    """The named preset with top-level fields replaced; InputError for an unknown name."""
    if name not in PRESETS:
        raise InputError(f"unknown synth preset {name!r}; choose one of {sorted(PRESETS)}")
    return replace(PRESETS[name], **overrides)  # type: ignore[arg-type]
