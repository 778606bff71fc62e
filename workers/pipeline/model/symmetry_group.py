"""Symmetry group of a library object: the spec, its JSON form, and pose errors modulo it.

(Detection from a surface cloud: :mod:`workers.pipeline.model.detect_symmetry`.)

**What "symmetric" means here.** A rotation ``S`` (4×4 ``object_from_object``, a rotation
about a point of the object) is a symmetry when the object's *surface geometry* maps onto
itself: the symmetric mean nearest-neighbour distance between the sampled surface and
its rotated copy is within ``max_mean_ratio`` of the sampling spacing, and at most
``max_far_fraction`` of points land more than ``far_ratio`` spacings off the surface.
Geometry, not colour, decides, because pose estimation registers geometry: scene colours
from photogrammetry are unreliable under shop-floor lighting, and a pose that only a
label distinguishes is still ambiguous to the geometric fit. Colour is measured too and
recorded as ``appearance_breaks`` (e.g. a can's label, a Rubik's cube's faces, the front
of a mustard bottle): pose estimation then *tries* to pick the right equivalent pose by
colour and says so, but the geometric group is what makes a pose ``ambiguous``.

For pose reporting, poses ``env_from_object @ S`` for every ``S`` in the group are
equally good fits; exactly one canonical pose is published (the one whose object "up"
agrees best with the environment's up, or closest to a previous pose) together with
the others.

**Spec (JSON-serialisable)**::

    {"kind": "none"}
    {"kind": "discrete", "rotations": [4x4, ...]}
    {"kind": "continuous", "axis": [x, y, z], "origin": [x, y, z], "rotations": [4x4, ...]}

``discrete``: the full finite group, identity first. ``continuous``: every rotation about
``axis`` through ``origin``, composed with each of ``rotations`` (identity first, plus e.g.
the 180° flip of a plain can).
    optional in each: "appearance_breaks": bool

Matrices are row-major nested lists, rotations about points of the object frame (metres).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from workers.pipeline.errors import InputError
from workers.pipeline.geometry import Mat4, as_mat4, axis_angle_matrix, rotation_angle_deg, skew

KINDS = ("none", "discrete", "continuous")


@dataclass(frozen=True, eq=False)
class SymmetrySpec:
    """Rotational symmetry group of an object (object frame, metres).

    ``rotations``: tuple of 4×4 ``object_from_object`` (identity first); for ``continuous``
    these are the extra discrete elements combined with every rotation about ``axis`` (unit
    (3,)) through ``origin`` ((3,), metres). ``appearance_breaks``: colour differs under at
    least one element.
    """

    kind: str = "none"
    rotations: tuple[Mat4, ...] = field(default_factory=lambda: (np.eye(4),))
    axis: NDArray[np.float64] | None = None
    origin: NDArray[np.float64] | None = None
    appearance_breaks: bool = False

    @property
    def is_symmetric(self) -> bool:
        """True when some pose other than the identity is equivalent."""
        return self.kind == "continuous" or len(self.rotations) > 1

    def continuous_rotation(self, angle_rad: float) -> Mat4:
        """4×4 rotation by ``angle_rad`` about the continuous axis (identity if none)."""
        if self.axis is None or self.origin is None:
            return np.eye(4)
        return rotation_about(self.axis, angle_rad, self.origin)

    def sample(self, n_angles: int = 12) -> list[Mat4]:
        """Finite list of group elements (continuous: ``n_angles`` steps per discrete element)."""
        if self.kind != "continuous":
            return list(self.rotations)
        out = []
        for s in self.rotations:
            for k in range(n_angles):
                out.append(self.continuous_rotation(2 * np.pi * k / n_angles) @ s)
        return out


NO_SYMMETRY = SymmetrySpec()


def rotation_about(
    axis: NDArray[np.float64], angle_rad: float, origin: NDArray[np.float64]
) -> Mat4:
    """4×4 rotation by ``angle_rad`` about the line through ``origin`` along ``axis``."""
    r = axis_angle_matrix(axis, angle_rad)
    out = np.eye(4)
    out[:3, :3] = r
    out[:3, 3] = origin - r @ origin
    return out


def _check_rotation(m: Any, what: str) -> Mat4:
    a = np.asarray(m, dtype=np.float64)
    if a.shape != (4, 4) or not np.isfinite(a).all():
        raise InputError(f"symmetry {what} must be a finite 4×4 matrix")
    r = a[:3, :3]
    if not np.allclose(r @ r.T, np.eye(3), atol=1e-3) or np.linalg.det(r) < 0.99:
        raise InputError(f"symmetry {what} is not a proper rotation")
    if not np.allclose(a[3], [0, 0, 0, 1], atol=1e-9):
        raise InputError(f"symmetry {what} must have last row 0 0 0 1")
    return a


SPEC_KEYS = frozenset({"kind", "rotations", "axis", "origin", "appearance_breaks"})


def spec_from_json(raw: Any) -> SymmetrySpec:
    """Parse and validate a spec (format in the module docstring); InputError if invalid."""
    if not isinstance(raw, dict) or raw.get("kind") not in KINDS:
        raise InputError(f"symmetry must be an object with kind in {KINDS}, got {raw!r:.200}")
    unknown = sorted(set(raw) - SPEC_KEYS)
    if unknown:
        raise InputError(f"symmetry has unknown keys {unknown}; it takes {sorted(SPEC_KEYS)}")
    kind = raw["kind"]
    brk = bool(raw.get("appearance_breaks", False))
    if kind == "none":
        return SymmetrySpec(appearance_breaks=brk)
    rots_raw = raw.get("rotations", [np.eye(4).tolist()] if kind == "continuous" else None)
    if not isinstance(rots_raw, list) or not rots_raw:
        raise InputError("symmetry rotations must be a non-empty list of 4×4 matrices")
    rots = [_check_rotation(m, f"rotations[{i}]") for i, m in enumerate(rots_raw)]
    if not any(rotation_angle_deg(r[:3, :3]) < 1e-3 for r in rots):
        rots.insert(0, np.eye(4))
    rots.sort(key=lambda r: rotation_angle_deg(r[:3, :3]))
    if kind == "discrete":
        return SymmetrySpec("discrete", tuple(rots), appearance_breaks=brk)
    axis = np.asarray(raw.get("axis"), dtype=np.float64)
    origin = np.asarray(raw.get("origin", [0.0, 0.0, 0.0]), dtype=np.float64)
    if axis.shape != (3,) or origin.shape != (3,) or not np.isfinite([*axis, *origin]).all():
        raise InputError("continuous symmetry needs axis [x, y, z] and origin [x, y, z]")
    norm = float(np.linalg.norm(axis))
    if norm < 1e-9:
        raise InputError("continuous symmetry axis must be non-zero")
    return SymmetrySpec("continuous", tuple(rots), axis / norm, origin, brk)


def spec_to_json(spec: SymmetrySpec) -> dict[str, Any]:
    """JSON form of a spec (inverse of :func:`spec_from_json`)."""
    out: dict[str, Any] = {"kind": spec.kind}
    if spec.kind != "none":
        out["rotations"] = [np.round(r, 9).tolist() for r in spec.rotations]
    if spec.kind == "continuous":
        assert spec.axis is not None and spec.origin is not None
        out["axis"] = spec.axis.tolist()
        out["origin"] = spec.origin.tolist()
    out["appearance_breaks"] = spec.appearance_breaks
    return out


def symmetric_pose_error(
    estimated_env_from_object: ArrayLike,
    true_env_from_object: ArrayLike,
    symmetry: SymmetrySpec,
    point_object: ArrayLike | None = None,
) -> tuple[float, float]:
    """(metres, degrees) pose error minimised over the symmetry group: the equivalent pose
    with the smallest rotation error, and its translation error measured at
    ``point_object`` ((3,), object frame; default the symmetry origin for continuous
    symmetry, else the object origin). Continuous symmetry is solved in closed form."""
    est = as_mat4(estimated_env_from_object, "estimated")
    true = as_mat4(true_env_from_object, "true")
    if point_object is None:
        point = (
            symmetry.origin
            if symmetry.kind == "continuous" and symmetry.origin is not None
            else np.zeros(3)
        )
    else:
        point = np.asarray(point_object, dtype=np.float64).reshape(3)
    if symmetry.kind == "continuous" and symmetry.axis is not None:
        # trace(R_true^T R_est R_axis(θ) R_d) = A + B cos θ + C sin θ: maximise in closed form
        ax = symmetry.axis
        k = skew(ax)
        elements = []
        for d in symmetry.rotations:
            m = d[:3, :3] @ true[:3, :3].T @ est[:3, :3]
            a_ = float(ax @ m @ ax)
            b_ = float(np.trace(m)) - a_
            c_ = float(np.trace(m @ k))
            elements.append(symmetry.continuous_rotation(float(np.arctan2(c_, b_))) @ d)
        stack = np.stack(elements)
    else:
        stack = np.stack(list(symmetry.rotations))
    cand = est @ stack  # (K, 4, 4)
    rel = np.einsum("ji,kjl->kil", true[:3, :3], cand[:, :3, :3])  # R_true^T R_k
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    best = int(np.argmax(cos))
    p_est = cand[best, :3, :3] @ point + cand[best, :3, 3]
    p_true = true[:3, :3] @ point + true[:3, 3]
    return float(np.linalg.norm(p_est - p_true)), float(np.degrees(np.arccos(cos[best])))
