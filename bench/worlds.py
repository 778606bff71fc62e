"""The tuning and test worlds of the scenario benchmark: a split you may not tune on.

Options and thresholds are tuned on :data:`TUNING` only; :data:`TEST` holds other objects,
other rooms and other seeds, and is run to report, never to choose a value. The sets share
no YCB object, no room preset (the test rooms use layouts, furniture and textures the
tuning rooms do not) and no seed; ``tests/bench/test_worlds.py`` checks it.

Each :class:`World` is one before/after scene: its scenario, its objects (the library of
that scene; the last non-symmetric one is the generator's spare, the object that appears in
added / swapped / multiple), a room and camera path preset of the generator, a seed, the
object the change acts on and the distractors (objects outside the library, which must come
out unidentified). :func:`real_camera` gives each world's real-camera variant.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from workers.pipeline.synth import (
    PATH_PRESETS,
    REAL_CAMERA,
    ROOM_PRESETS,
    EffectsOptions,
    SynthOptions,
)

#: The five objects of the original bench and four more: flat (two clamps, hammer), tall
#: (drill, mustard bottle), a box (wood block), round (two cans) and a mug.
TUNING_OBJECTS: tuple[str, ...] = (
    "power_drill",
    "large_clamp",
    "mustard_bottle",
    "master_chef_can",
    "hammer",
    "extra_large_clamp",
    "mug",
    "tomato_soup_can",
    "wood_block",
)
#: The other nine: flat (adjustable wrench, padlock), tall (pitcher, bleach and window
#: cleaner bottles), boxes (cracker and sugar boxes, Rubik's cube) and the bowl.
TEST_OBJECTS: tuple[str, ...] = (
    "adjustable_wrench",
    "padlock",
    "pitcher_base",
    "cracker_box",
    "sugar_box",
    "bleach_cleanser",
    "windex_bottle",
    "bowl",
    "rubiks_cube",
)


@dataclass(frozen=True)
class World:
    """One benchmark scene: the generator's inputs besides the base preset."""

    name: str
    scenario: str
    objects: tuple[str, ...]
    room: str
    path: str
    seed: int
    target: str | None = None
    distractors: tuple[str, ...] = ()
    lying: tuple[str, ...] = ()

    def options(self, base: SynthOptions) -> SynthOptions:
        """``base`` (e.g. the "bench" preset) in this world's room, path (``base``'s number
        of views kept), target, distractors and the objects set down off their base."""
        path = replace(PATH_PRESETS[self.path], n_views=base.path.n_views)
        return replace(
            base,
            room=ROOM_PRESETS[self.room],
            path=path,
            target=self.target,
            distractors=self.distractors,
            lying=self.lying,
        )


TUNING: tuple[World, ...] = (
    World(
        "moved",
        "moved",
        ("power_drill", "large_clamp", "mustard_bottle", "master_chef_can", "hammer"),
        "closed",
        "ring",
        1,
    ),
    World(
        "flat_added_on_table",
        "added",
        ("power_drill", "mug", "wood_block", "tomato_soup_can", "extra_large_clamp"),
        "closed_table",
        "ring",
        2,
    ),
    World(
        "box_swapped_for_bottle",
        "swapped",
        ("large_clamp", "wood_block", "master_chef_can", "hammer", "mustard_bottle"),
        "two_walls",
        "low_high",
        3,
        target="wood_block",
    ),
    World(
        "flat_removed_with_distractors",
        "removed",
        ("power_drill", "hammer", "mug", "tomato_soup_can", "large_clamp"),
        "two_walls_table",
        "wide_high",
        4,
        target="hammer",
        distractors=("unknown_box", "column"),
    ),
    World(
        "multiple",
        "multiple",
        ("mustard_bottle", "extra_large_clamp", "master_chef_can", "wood_block", "mug"),
        "closed",
        "low_high",
        5,
    ),
    # the set's lowest objects on the floor: the hammer (3.3 cm) moved, the large clamp
    # (3.9 cm, 12 × 17 cm) removed; what the seen check and identification of flat
    # objects are tuned on
    World(
        "flat_moved",
        "moved",
        ("hammer", "mug", "tomato_soup_can", "power_drill", "large_clamp"),
        "two_walls",
        "low_high",
        6,
        target="hammer",
    ),
    World(
        "clamp_removed",
        "removed",
        ("large_clamp", "power_drill", "mug", "master_chef_can", "extra_large_clamp"),
        "closed",
        "ring",
        7,
        target="large_clamp",
    ),
    # objects on their side or upside down (each on a face of its hull it can rest on,
    # drawn at random), the drill moved: what the upright rule costs where up is not up
    World(
        "lying_moved",
        "moved",
        ("power_drill", "mug", "wood_block", "mustard_bottle", "hammer"),
        "closed",
        "ring",
        8,
        target="power_drill",
        lying=("power_drill", "mug", "wood_block", "mustard_bottle", "hammer"),
    ),
    # the same draw stands all four upside down: the mug the upright rule was made for,
    # the cans (round, their ends differ) and the bottle; a can removed
    World(
        "upside_down_removed",
        "removed",
        ("mug", "master_chef_can", "tomato_soup_can", "mustard_bottle", "large_clamp"),
        "two_walls",
        "low_high",
        9,
        target="master_chef_can",
        lying=("mug", "master_chef_can", "tomato_soup_can", "mustard_bottle"),
    ),
)

TEST: tuple[World, ...] = (
    World(
        "flat_added",
        "added",
        ("pitcher_base", "sugar_box", "bowl", "bleach_cleanser", "adjustable_wrench"),
        "one_wall",
        "low_high",
        101,
    ),
    World(
        "flat_removed",
        "removed",
        ("padlock", "cracker_box", "windex_bottle", "rubiks_cube", "pitcher_base"),
        "closed_small",
        "low_high",
        102,
        target="padlock",
    ),
    World(
        "flat_moved_beside_shelf",
        "moved",
        ("adjustable_wrench", "sugar_box", "bowl", "windex_bottle", "padlock"),
        "one_wall_shelf",
        "wide_high",
        103,
        target="adjustable_wrench",
    ),
    World(
        "box_swapped_for_bottle",
        "swapped",
        ("cracker_box", "pitcher_base", "bowl", "padlock", "bleach_cleanser"),
        "shelf_room",
        "wide_high",
        104,
        target="cracker_box",
    ),
    World(
        "distractors_only",
        "no_change",
        ("sugar_box", "windex_bottle", "rubiks_cube", "bowl", "pitcher_base"),
        "one_wall",
        "low_high",
        105,
        distractors=("unknown_box", "column"),
    ),
    World(
        "multiple",
        "multiple",
        ("bleach_cleanser", "padlock", "bowl", "sugar_box", "adjustable_wrench"),
        "closed_small",
        "low_high",
        106,
    ),
    World(
        "lying_moved",
        "moved",
        ("cracker_box", "sugar_box", "pitcher_base", "windex_bottle", "padlock"),
        "one_wall",
        "low_high",
        107,
        target="cracker_box",
        lying=("cracker_box", "sugar_box", "pitcher_base", "windex_bottle", "padlock"),
    ),
)

SETS: dict[str, tuple[World, ...]] = {"tuning": TUNING, "test": TEST}

# lenses of the real-camera variants, in turn: declared OPENCV, declared SIMPLE_RADIAL,
# and the OPENCV lens left to structure from motion (no intrinsics in cameras.json)
_LENSES: tuple[EffectsOptions, ...] = (
    REAL_CAMERA,
    replace(REAL_CAMERA, distortion="SIMPLE_RADIAL", k1=-0.09, k2=0.0, p1=0.0, p2=0.0),
    replace(REAL_CAMERA, declare_intrinsics=False),
)


def real_camera(options: SynthOptions, index: int) -> SynthOptions:
    """The real-camera variant of the world at ``index`` of its set: a distorting lens
    (declared OPENCV, declared SIMPLE_RADIAL, or undeclared, in turn), the after capture
    brighter and warmer, per-image exposure jitter, motion blur, sensor noise σ 2.5 and
    JPEG quality 90. Without declared intrinsics the poses are not written either."""
    effects = _LENSES[index % len(_LENSES)]
    look = replace(options.look, noise_sigma=2.5, jpeg_quality=90)
    write_poses = options.write_poses and effects.declare_intrinsics
    return replace(options, effects=effects, look=look, write_poses=write_poses)
