"""The benchmark's split: tuning and test worlds share no object, room or seed, and every
world builds the scene it claims (flat objects, a box swapped for a bottle, distractors)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from bench.worlds import SETS, TEST, TEST_OBJECTS, TUNING, TUNING_OBJECTS, World, real_camera
from workers.pipeline.synth import (
    PRESETS,
    ROOM_PRESETS,
    YCB_OBJECTS,
    CameraOptions,
    ObjectModel,
    Scenario,
    build_scenario,
    render_capture,
    ycb_models,
)

SMALL = CameraOptions(width=160, height=120, focal_px=130.0)
FLAT = {"adjustable_wrench", "padlock", "large_clamp", "extra_large_clamp", "hammer"}
BOXES = {"cracker_box", "sugar_box", "wood_block"}
BOTTLES = {"mustard_bottle", "bleach_cleanser", "windex_bottle"}


def test_sets_are_disjoint_in_objects_rooms_and_seeds() -> None:
    assert set(TUNING_OBJECTS).isdisjoint(TEST_OBJECTS)
    assert sorted(TUNING_OBJECTS + TEST_OBJECTS) == sorted(YCB_OBJECTS)
    for worlds, objects in ((TUNING, TUNING_OBJECTS), (TEST, TEST_OBJECTS)):
        assert all(set(w.objects) <= set(objects) for w in worlds)
    assert {w.room for w in TUNING}.isdisjoint({w.room for w in TEST})
    assert {w.seed for w in TUNING}.isdisjoint({w.seed for w in TEST})
    # the test rooms' textures, and their open one-wall layout and shelf, never appear in
    # tuning
    tuning_rooms = [ROOM_PRESETS[w.room] for w in TUNING]
    test_rooms = [ROOM_PRESETS[w.room] for w in TEST]
    assert {r.texture_variant for r in tuning_rooms}.isdisjoint(
        {r.texture_variant for r in test_rooms}
    )
    assert not any(r.shelf or r.layout == "one_wall" for r in tuning_rooms)
    assert all(len({w.name for w in worlds}) == len(worlds) for worlds in SETS.values())


def _built(world: World, models: dict[str, ObjectModel]) -> Scenario:
    options = world.options(replace(PRESETS["bench"], camera=SMALL))
    return build_scenario(world.scenario, [models[n] for n in world.objects], world.seed, options)


@pytest.fixture(scope="module")
def models(shared_data: Path) -> dict[str, ObjectModel]:
    return {m.name: m for m in ycb_models(shared_data / "ycb", YCB_OBJECTS)}


def test_test_worlds_cover_the_cases(models: dict[str, ObjectModel]) -> None:
    """The test set has flat objects added, removed and moved, a box swapped for a bottle
    in its place, and distractors whose changes are unidentified."""
    seen: set[str] = set()
    for world in TEST:
        scenario = _built(world, models)
        for change in scenario.changes:
            if change.get("unidentified"):
                assert change["object"] is None
                seen.add("distractor")
            elif change["object"] in FLAT:
                seen.add(f"flat_{change['type']}")
            if change["type"] == "swapped":
                assert change["replaced_object"] in BOXES and change["object"] in BOTTLES
                seen.add("box_to_bottle")
    assert {"flat_added", "flat_removed", "flat_moved", "box_to_bottle", "distractor"} <= seen


def test_every_world_builds_and_its_real_camera_variant_renders(
    models: dict[str, ObjectModel],
) -> None:
    lenses = []
    for worlds in SETS.values():
        for index, world in enumerate(worlds):
            scenario = _built(world, models)
            assert scenario.changes or world.scenario == "no_change"
            real = real_camera(world.options(replace(PRESETS["bench"], camera=SMALL)), index)
            lenses.append((real.effects.distortion, real.effects.declare_intrinsics))
            assert real.effects.active and real.look.jpeg_quality == 90
    world = TEST[0]
    options = real_camera(world.options(replace(PRESETS["bench"], camera=SMALL)), 0)
    options = replace(options, path=replace(options.path, n_views=1))
    scenario = build_scenario(
        world.scenario,
        [models[n] for n in world.objects],
        world.seed,
        options,
    )
    (_, view) = next(iter(render_capture(scenario, "after", options)))
    assert float(view.image.std()) > 10.0 and (view.instance >= 0).any()
    assert set(lenses) == {("OPENCV", True), ("SIMPLE_RADIAL", True), ("OPENCV", False)}


def test_every_object_is_in_view(models: dict[str, ObjectModel]) -> None:
    """The camera paths cover the object field: at 160×120 with 20 views, every object shows
    at least 6 pixels (the bench detector's 150 px at 800×600, scaled) in ≥ 20 % of the
    views of each capture, and every changed object in ≥ 50 %."""
    for world in TUNING + TEST:
        options = world.options(replace(PRESETS["bench"], camera=SMALL))
        options = replace(options, path=replace(options.path, n_views=20))
        scenario = _built(world, models)
        changed = {c["instance_id"] for c in scenario.changes}
        changed |= {c["replaced_instance_id"] for c in scenario.changes}
        for capture in ("before", "after"):
            placements = scenario.capture(capture)
            seen = np.zeros(len(placements))
            for _, view in render_capture(scenario, capture, options):
                seen += [np.count_nonzero(view.instance == i) >= 6 for i in range(len(seen))]
            share = seen / options.path.n_views
            for p, s in zip(placements, share, strict=True):
                least = 0.5 if p.instance_id in changed else 0.2
                assert s >= least, (world.name, capture, p.model.name, s)
