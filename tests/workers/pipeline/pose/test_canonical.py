"""Which of a symmetric object's equivalent poses is published (pose.canonical): colour
chooses among those standing the same way up, whatever way up that is."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from workers.pipeline.geometry import Mat4, make_rigid, rotation_about_unit_axis
from workers.pipeline.model.symmetry_group import SymmetrySpec
from workers.pipeline.pose.canonical import _choose_equivalent

UP = np.array([0.0, 0.0, 1.0])
#: a box's shape group: the half turns about its three axes; its print breaks it
BOX = SymmetrySpec(
    kind="discrete",
    rotations=(
        np.eye(4),
        *(make_rigid(rotation_about_unit_axis(np.eye(3)[k], np.pi), np.zeros(3)) for k in range(3)),
    ),
    appearance_breaks=True,
)


def _turn(axis: tuple[float, float, float], deg: float) -> Mat4:
    unit = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    return make_rigid(rotation_about_unit_axis(unit, np.radians(deg)), np.zeros(3))


def _colour_of(true: Mat4) -> Callable[[Mat4], float]:
    def colour(pose: Mat4) -> float:
        return 0.5 if np.allclose(pose[:3, :3], true[:3, :3], atol=1e-6) else 0.05

    return colour


def test_colour_chooses_among_every_side_of_a_lying_box() -> None:
    # on its side (object z horizontal), tilted 1.1° by the fit: its equivalents' object up
    # lies at 88.9°-91.1° from the environment's up, on either side of the horizontal
    fitted = _turn((1.0, 0.0, 0.0), 88.9)
    ups = [(fitted @ s)[:3, 2] @ UP for s in BOX.rotations]
    assert max(ups) - min(ups) > 0.03  # a cosine window of 0.02 would leave some out
    for s in BOX.rotations:
        true = fitted @ s
        picked = _choose_equivalent(fitted, BOX, UP, UP, None, _colour_of(true), 0.02)
        assert picked.chosen_by == "colour"
        assert np.allclose(picked.env_from_object, true)


def test_an_upright_box_is_never_published_upside_down_for_its_colour() -> None:
    fitted = _turn((0.0, 0.0, 1.0), 30.0) @ _turn((1.0, 0.0, 0.0), 2.0)
    flipped = fitted @ BOX.rotations[1]  # upside down, its colour the best
    picked = _choose_equivalent(fitted, BOX, UP, UP, None, _colour_of(flipped), 0.02)
    assert picked.chosen_by == "up"
    assert (picked.env_from_object[:3, 2] @ UP) > 0.99
    yawed = fitted @ BOX.rotations[3]  # half a turn about up: same way up, colour decides
    picked = _choose_equivalent(fitted, BOX, UP, UP, None, _colour_of(yawed), 0.02)
    assert picked.chosen_by == "colour" and np.allclose(picked.env_from_object, yawed)


#: a can's shape group: any turn about its axis, and end over end; its label breaks it
CAN = SymmetrySpec(
    kind="continuous",
    rotations=(np.eye(4), _turn((1.0, 0.0, 0.0), 180.0)),
    axis=np.array([0.0, 0.0, 1.0]),
    origin=np.zeros(3),
    appearance_breaks=True,
)


def test_a_cans_colours_say_which_end_is_up() -> None:
    fitted = _turn((0.0, 0.0, 1.0), 40.0)  # fitted upright; the label reads upside down

    def upside_down_label(pose: Mat4) -> float:
        return 0.4 if pose[:3, 2] @ UP < 0 else 0.1

    picked = _choose_equivalent(fitted, CAN, UP, UP, None, upside_down_label, 0.02)
    assert picked.chosen_by == "colour" and picked.env_from_object[:3, 2] @ UP < -0.99
    # colours that do not tell the ends apart leave it upright, chosen by "up" (a guess)
    picked = _choose_equivalent(fitted, CAN, UP, UP, None, lambda pose: 0.3, 0.02)
    assert picked.chosen_by == "up" and picked.env_from_object[:3, 2] @ UP > 0.99
