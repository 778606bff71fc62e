"""Matching pairs beyond exhaustive matching, and the dense working scale."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from tests.workers.pipeline.reconstruct_scene import write_scene
from workers.pipeline.reconstruct import options_from_preset, parse_cameras
from workers.pipeline.reconstruct.common import list_images
from workers.pipeline.reconstruct.mvs import working_scale
from workers.pipeline.reconstruct.pairs import (
    bag_of_words,
    matching_pairs,
    retrieval_pairs,
    sequential_pairs,
)
from workers.pipeline.reconstruct.sfm import run_sfm


def test_sequential_pairs_are_the_next_images_and_powers_of_two() -> None:
    assert sequential_pairs(5, 2, quadratic=False) == {
        (0, 1),
        (0, 2),
        (1, 2),
        (1, 3),
        (2, 3),
        (2, 4),
        (3, 4),
    }
    assert (0, 8) in sequential_pairs(20, 4) and (0, 5) not in sequential_pairs(20, 4)


def _ring_descriptors(n: int, places: int = 10, seed: int = 0) -> list[np.ndarray]:
    """n photos round a ring of ``places`` places; photo i shows place i·places/n: 300
    descriptors near that place's own 6 feature looks (of 128 uint8)."""
    rng = np.random.default_rng(seed)
    looks = rng.integers(20, 236, (places, 6, 128))
    out = []
    for i in range(n):
        centres = looks[i * places // n][rng.integers(0, 6, 300)]
        noisy = centres + rng.integers(-10, 11, centres.shape)
        out.append(noisy.astype(np.uint8))
    return out


def test_retrieval_pairs_images_of_the_same_place() -> None:
    desc = _ring_descriptors(40)
    hist = bag_of_words(desc, words=32, per_image=200)
    assert hist.shape == (40, 32)
    np.testing.assert_allclose(np.linalg.norm(hist, axis=1), 1.0, rtol=1e-5)
    pairs = retrieval_pairs(hist, 3)
    same_place = [i // 4 == j // 4 for i, j in pairs]
    assert np.mean(same_place) > 0.9


def test_matching_pairs_close_the_loop_and_grow_linearly() -> None:
    # photos 0-3 and 36-39 show the same place as each other only in the retrieval sense
    desc = _ring_descriptors(40)
    desc[-4:] = _ring_descriptors(40)[:4]
    chosen = matching_pairs(desc, overlap=3, loop_neighbours=3)
    assert any(i < 4 and j >= 36 for i, j in chosen)
    assert len(chosen) < 40 * (3 + 3 + 3)
    assert len(matching_pairs(desc, overlap=3, loop_neighbours=0)) == len(sequential_pairs(40, 3))


def test_working_scale_bounds_the_long_side_only_when_larger() -> None:
    assert working_scale(1152, 864, 1.0, 1600) == 1.0
    assert working_scale(4000, 3000, 1.0, 1600) == 0.4
    assert working_scale(4000, 3000, 0.25, 1600) == 0.25
    assert working_scale(4000, 3000, 1.0, -1) == 1.0


def test_sfm_beyond_exhaustive_matches_the_listed_pairs(tmp_path: Path) -> None:
    """Past ``exhaustive_max_images`` SfM matches sequential + retrieval pairs
    (sfm/pairs.txt) and still registers every photo of a ring."""
    write_scene(tmp_path / "scene", n_views=10)
    raw = json.loads((tmp_path / "scene" / "cameras.json").read_text())
    names = list_images(tmp_path / "scene" / "images")
    options = options_from_preset(exhaustive_max_images=3, sequential_overlap=2, loop_neighbours=2)
    cams = parse_cameras({"intrinsics": raw["intrinsics"]})
    model = run_sfm(tmp_path / "scene" / "images", tmp_path / "work", names, options, cams)
    listed = (tmp_path / "work" / "sfm" / "pairs.txt").read_text().splitlines()
    assert len(listed) < 10 * 9 // 2
    assert all(len(line.split()) == 2 for line in listed)
    assert len(model.views) == 10


def test_global_mapping_past_incremental_max_images_registers_every_view(tmp_path: Path) -> None:
    """Past ``incremental_max_images`` SfM maps globally (GLOMAP); the ring scene's views
    all register, with the known intrinsics held fixed, and reproject as tightly."""
    write_scene(tmp_path / "scene", n_views=10)
    raw = json.loads((tmp_path / "scene" / "cameras.json").read_text())
    names = list_images(tmp_path / "scene" / "images")
    cams = parse_cameras({"intrinsics": raw["intrinsics"]})
    options = options_from_preset(incremental_max_images=5)
    model = run_sfm(tmp_path / "scene" / "images", tmp_path / "work", names, options, cams)
    assert len(model.views) == 10
    assert model.mean_reprojection_error_px < 1.0
    assert {v.intrinsics.params for v in model.views} == {tuple(raw["intrinsics"]["params"])}
