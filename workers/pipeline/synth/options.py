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
    # (radius, height) rings in metres; empty: the single wavy ring above. Views go round
    # the rings in turn (view k on ring k mod len), each ring an even sweep of ``arc_deg``.
    rings_m: tuple[tuple[float, float], ...] = ()


@dataclass(frozen=True)
class RoomOptions:
    """Room, reference markers and the optional table and shelf.

    ``layout``: "closed" (four walls), "one_wall" (open floor, the wall at +y), or
    "two_walls" (open floor, the walls at +y and +x: a corner). ``texture_variant`` 0 is
    the original look; 1.. pick other floor and wall colours and noise seeds. The shelf is
    an open unit (two boards on side panels) whose top board is a support like the table.
    """

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
    layout: str = "closed"
    texture_variant: int = 0
    shelf: bool = False
    shelf_size_m: tuple[float, float, float] = (0.4, 1.0, 0.7)
    shelf_centre_m: tuple[float, float] = (1.25, 0.0)


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
class EffectsOptions:
    """Real-camera effects applied while rendering; the defaults change nothing.

    ``distortion``: None (pinhole), "OPENCV" (``k1, k2, p1, p2``) or "SIMPLE_RADIAL"
    (``k1`` only): the images are rendered through that lens and cameras.json declares it.
    ``declare_intrinsics`` False leaves cameras.json without intrinsics (the pipeline must
    self-calibrate; without poses no cameras.json is written). ``capture_gain`` and
    ``capture_white_balance`` scale the linear image per capture (before, after), RGB gains;
    ``exposure_jitter`` is the standard deviation of a per-image log gain;
    ``motion_blur_px`` the largest blur length (a line of random direction, per image).
    Per-image draws come from their own generator of (seed, capture, view).
    """

    distortion: str | None = None
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    declare_intrinsics: bool = True
    capture_gain: tuple[float, float] = (1.0, 1.0)
    capture_white_balance: tuple[tuple[float, float, float], tuple[float, float, float]] = (
        (1.0, 1.0, 1.0),
        (1.0, 1.0, 1.0),
    )
    exposure_jitter: float = 0.0
    motion_blur_px: float = 0.0

    @property
    def active(self) -> bool:
        """Whether any effect is on (False: images as without effects, byte for byte)."""
        return self != EffectsOptions()


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
    effects: EffectsOptions = field(default_factory=EffectsOptions)
    # objects outside the library (:data:`DISTRACTORS` names) added in the after capture;
    # their ground-truth changes are marked unidentified
    distractors: tuple[str, ...] = ()
    # the model the change acts on (removed, moved or swapped out); None: drawn at random
    target: str | None = None
    # models set down on another face than their base (on a side, upside down), drawn at
    # random among the faces they can rest on: poses the upright placements never show
    lying: tuple[str, ...] = ()


LAYOUTS: tuple[str, ...] = ("closed", "one_wall", "two_walls")
DISTRACTORS: tuple[str, ...] = ("unknown_box", "column")

#: Effects of a handheld consumer camera: OPENCV barrel distortion, the after capture
#: brighter and warmer, ±8 % exposure per image, up to 1.5 px of motion blur.
REAL_CAMERA = EffectsOptions(
    distortion="OPENCV",
    k1=-0.12,
    k2=0.03,
    p1=0.0008,
    p2=-0.0005,
    capture_gain=(1.0, 1.15),
    capture_white_balance=((1.0, 1.0, 1.0), (1.06, 1.0, 0.92)),
    exposure_jitter=0.08,
    motion_blur_px=1.5,
)


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
    "real_camera": SynthOptions(
        write_poses=False,
        path=PathOptions(n_views=40),
        look=LookOptions(noise_sigma=2.5, jpeg_quality=90),
        detection=DetectionOptions(box_jitter_px=2.0, miss_rate=0.05, false_positive_rate=0.02),
        effects=REAL_CAMERA,
    ),
}


#: Named rooms: the original closed room, and wider worlds (open floors with one or two
#: walls, tables, a shelf, other sizes and textures). The marker sheet is always on the floor.
ROOM_PRESETS: dict[str, RoomOptions] = {
    "closed": RoomOptions(),
    "closed_table": RoomOptions(table=True),
    "closed_small": RoomOptions(size_m=5.0, texture_variant=3),
    "one_wall": RoomOptions(layout="one_wall", size_m=8.0, texture_variant=1),
    "one_wall_shelf": RoomOptions(layout="one_wall", size_m=8.0, texture_variant=1, shelf=True),
    "two_walls": RoomOptions(layout="two_walls", size_m=7.0, texture_variant=2),
    "two_walls_table": RoomOptions(
        layout="two_walls", size_m=7.0, texture_variant=2, table=True, table_size_m=(0.9, 0.5, 0.5)
    ),
    "shelf_room": RoomOptions(size_m=6.5, texture_variant=4, shelf=True),
}

#: Named camera paths: the original wavy ring, and two-ring orbits (radius, height). Rooms
#: with a table or shelf need "wide_high" (the others pass through what stands on them).
PATH_PRESETS: dict[str, PathOptions] = {
    "ring": PathOptions(n_views=40),
    "low_high": PathOptions(n_views=40, rings_m=((1.5, 0.7), (1.8, 1.6)), radius_jitter_m=0.1),
    # for rooms with a table or shelf: every camera outside them and above what stands there
    "wide_high": PathOptions(n_views=40, rings_m=((1.9, 1.1), (2.05, 1.9)), radius_jitter_m=0.1),
}


def preset(name: str, **overrides: object) -> SynthOptions:
    """The named preset with top-level fields replaced; InputError for an unknown name."""
    if name not in PRESETS:
        raise InputError(f"unknown synth preset {name!r}; choose one of {sorted(PRESETS)}")
    return replace(PRESETS[name], **overrides)  # type: ignore[arg-type]
