"""The in-plane fit of a flat object's outline seen from above
(workers.pipeline.pose.top_view): scans sampled from boxes (object frame, metres) with noise,
edges smeared down towards the floor as stereo leaves a thin object's rim, and the floor
seen around it (not under it)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from tests.workers.pipeline.pose.test_final_fit import box_surface, errors, turn
from workers.pipeline.geometry import transform_points
from workers.pipeline.model.symmetry_group import NO_SYMMETRY
from workers.pipeline.pose.top_view import Outline, fit_top_view, outline_costs

FLOOR = np.array([0.0, 0.0, 1.0, 0.0])


def l_plate(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) points and normals of an L of two 12 mm thick plates, 16 × 3 cm and
    3 × 8 cm, base at z = 0 (a wrench's outline, no symmetry; they overlap at x 5-8 cm,
    y 1.5 cm)."""
    a, an = box_surface((0.16, 0.03, 0.012), 6000, seed)
    b, bn = box_surface((0.03, 0.08, 0.012), 3000, seed + 1)
    b += np.array([0.065, 0.055, 0.0])
    return np.vstack([a, b]), np.vstack([an, bn])


def model_of(points: np.ndarray) -> SimpleNamespace:
    """What the fit needs of a model without symmetry: samples, centre, symmetry."""
    return SimpleNamespace(points=points, centre_object=points.mean(axis=0), symmetry=NO_SYMMETRY)


def smeared_scan(
    points: np.ndarray, normals: np.ndarray, env_from_object: np.ndarray, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """(object scan, floor) in the env frame: the faces a camera above sees, 1 mm noise;
    a third of the side points dragged down to 1-3 mm above the floor and 0-2 mm outwards
    (the smear that makes point-to-plane fits turn a flat object); floor points 1 mm
    noisy on a 40 cm square, none under the object."""
    rng = np.random.default_rng(seed)
    keep = normals[:, 2] > -0.5
    p = points[keep] + rng.normal(scale=0.001, size=(int(keep.sum()), 3))
    side = np.abs(normals[keep][:, 2]) < 0.5
    smear = side & (rng.random(len(p)) < 0.33)
    p[smear, 2] = rng.uniform(0.001, 0.003, int(smear.sum()))
    p[smear] += normals[keep][smear] * rng.uniform(0.0, 0.002, (int(smear.sum()), 1))
    floor = np.column_stack(
        [rng.uniform(-0.2, 0.2, (40000, 2)), rng.normal(scale=0.001, size=40000)]
    )
    under_a = (np.abs(floor[:, 0]) <= 0.08) & (np.abs(floor[:, 1]) <= 0.015)
    under_b = (np.abs(floor[:, 0] - 0.065) <= 0.015) & (np.abs(floor[:, 1] - 0.055) <= 0.04)
    floor = floor[~(under_a | under_b)]
    return transform_points(env_from_object, p), transform_points(env_from_object, floor)


def test_a_flat_object_turned_and_shifted_on_the_floor_is_fitted_back_to_its_outline() -> None:
    pts, nrm = l_plate(0)
    true = turn((0.0, 0.0, 25.0), (0.3, -0.1, 0.0))
    shape = model_of(pts)
    for seed in (1, 2):
        scene, floor = smeared_scan(pts, nrm, true, seed)
        starts = [
            turn((0.0, 0.0, 6.0), (0.003, -0.002, 0.0)) @ true,
            turn((0.0, 0.0, -9.0), (-0.002, 0.004, 0.0)) @ true,
        ]
        for start in starts:
            # 9° turns the L's far end 12 mm, beyond the window: the points are chosen
            # again around the fit until it settles
            fitted = fit_top_view(shape, [start], FLOOR, scene, floor, 0.008, 0.01)
            dt, dr = errors(fitted, true)
            assert dr < 0.2 and dt < 0.0005, (seed, dt, dr)
            # the fit only turns about the floor's normal and shifts across it
            assert abs(fitted[2, 3] - true[2, 3]) < 1e-9
            assert np.allclose(fitted[:3, 2], [0.0, 0.0, 1.0])
        # of two starts the one whose fit holds the scan best wins
        both = fit_top_view(shape, starts[::-1], FLOOR, scene, floor, 0.008, 0.01)
        assert errors(both, true)[1] < 0.2


def test_the_floor_seen_under_an_overhang_is_not_held_against_the_outline() -> None:
    # a 10 × 10 cm cap 2 cm thick on a 2 × 2 cm stem 5 cm tall: from above its outline is
    # the cap's; only the stem stands on the floor
    cap, _ = box_surface((0.10, 0.10, 0.02), 6000, 3)
    stem, _ = box_surface((0.02, 0.02, 0.05), 8000, 4)
    outline = Outline.create(
        np.vstack([cap + np.array([0.0, 0.0, 0.05]), stem]), np.array([0.0, 0.0, 1.0]), 0.03, 0.005
    )
    under_cap = np.array([[0.04, 0.0, 0.0], [0.0, -0.04, 0.0]])
    at_stem = np.array([[0.0, 0.0, 0.0]])
    beside = np.array([[0.07, 0.0, 0.0]])

    def value(grid: np.ndarray, p: np.ndarray) -> np.ndarray:
        ij = np.round(outline.cells(np.eye(4), p)).astype(int)
        return grid[ij[0], ij[1]]

    assert np.all(value(outline.outside_m, under_cap) == 0.0)  # inside the outline
    assert np.all(value(outline.inside_m, under_cap) == 0.0)  # the floor shows there
    assert value(outline.inside_m, at_stem)[0] > 0.005  # none shows under the stem
    assert 0.015 < value(outline.outside_m, beside)[0] < 0.025
    assert abs(outline.height_m - 0.07) < 0.002


def test_without_scan_points_near_its_outline_the_start_stays() -> None:
    pts, _ = l_plate(5)
    true = turn((0.0, 0.0, 10.0), (0.0, 0.0, 0.0))
    far = np.random.default_rng(6).uniform(0.5, 0.6, (500, 3))
    fitted = fit_top_view(model_of(pts), [true], FLOOR, far, np.zeros((0, 3)), 0.008, 0.016)
    assert np.array_equal(fitted, true)


def test_a_fit_that_would_turn_its_start_far_leaves_it_where_it_was() -> None:
    # started 45° off, the outline fit would leave the pose it refines (unbounded, it turns
    # it 135°, to the mirror of the true pose): the candidates' scores choose among poses
    # that far apart, so the start stays
    pts, nrm = l_plate(7)
    true = turn((0.0, 0.0, -30.0), (0.1, 0.2, 0.0))
    scene, floor = smeared_scan(pts, nrm, true, 8)
    start = turn((0.0, 0.0, 45.0), (0.0, 0.0, 0.0)) @ true
    fitted = fit_top_view(model_of(pts), [start], FLOOR, scene, floor, 0.008, 0.1)
    assert np.array_equal(fitted, start)


def test_the_outline_tells_a_flat_object_from_its_mirror_image() -> None:
    # the L turned over onto its other face (about its long axis) fits the scan's faces
    # almost as well, but its leg falls where the scan shows floor
    pts, nrm = l_plate(9)
    true = turn((0.0, 0.0, 40.0), (-0.2, 0.1, 0.0))
    scene, floor = smeared_scan(pts, nrm, true, 10)
    mirrored = true @ turn((180.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    mirrored[2, 3] -= transform_points(mirrored, pts)[:, 2].min()
    turned = turn((0.0, 0.0, 2.0), (0.0, 0.0, 0.0)) @ true
    shape = model_of(pts)
    right, twice, mirror, off = outline_costs(
        shape, [true, true, mirrored, turned], FLOOR, scene, floor, 0.008, 0.016
    )
    assert right == twice  # the same points for every pose
    assert mirror > 2.0 * right
    assert right < off < mirror
    assert outline_costs(shape, [], FLOOR, scene, floor, 0.008, 0.016) == []
    far = np.random.default_rng(11).uniform(0.5, 0.6, (100, 3))
    assert outline_costs(shape, [true], FLOOR, far, floor, 0.008, 0.016) == [float("inf")]
