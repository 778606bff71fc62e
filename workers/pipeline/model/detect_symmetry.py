"""Detect a library object's rotational symmetry group from its surface cloud (see
:mod:`workers.pipeline.model.symmetry_group` for what "symmetric" means and the spec).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from workers.pipeline.errors import InputError
from workers.pipeline.geometry import (
    Mat4,
    Points,
    as_points,
    perpendicular_pair,
    rotation_angle_deg,
)
from workers.pipeline.model.symmetry_group import SymmetrySpec, rotation_about

# distinct elements of the groups we detect (cyclic up to order 4, dihedral, octahedral)
# are at least 90° apart; closer candidates are the same element measured twice
DEDUPE_DEG = 30.0


@dataclass(frozen=True)
class SymmetryOptions:
    """Thresholds of symmetry detection, in units of the sampling spacing ``d0`` (mean
    distance from a sample to its nearest other sample); a perfectly symmetric surface
    gives a mean ratio of about 0.5 (scan figures: docs/decisions/pose.md)."""

    # surface samples scored per candidate rotation; raise for detailed objects, costs time
    n_eval: int = 1500
    # largest mean nearest-neighbour ratio of a symmetry, × d0; raise for noisy scans
    max_mean_ratio: float = 1.0
    # a rotated sample farther than this, × d0, is off the surface
    far_ratio: float = 3.0
    # largest share of rotated samples off the surface for a symmetry
    max_far_fraction: float = 0.02
    # coarse mean ratio, × d0, a candidate must beat before ICP refinement
    coarse_ratio: float = 3.0
    # principal moments closer than this (relative) make their axes' plane degenerate
    degenerate_gap: float = 0.1
    # angles, degrees, that must all be symmetries for an axis to count as continuous
    continuous_angles_deg: tuple[float, ...] = (23.0, 45.0, 67.0, 90.0, 131.0, 180.0, 247.0)
    # colour mismatch ratio above which colour breaks a symmetry (a label)
    colour_ratio: float = 1.8
    # largest discrete group closed from the accepted rotations
    max_group: int = 24
    # most candidate rotations refined by ICP, best coarse ratio first
    max_refinements: int = 40
    # largest refined mean ratio, × d0, of a near-symmetry (tried by pose estimation)
    near_ratio: float = 3.0
    # seed of the sample choice; detection is deterministic for a seed
    seed: int = 0


def _fibonacci_hemisphere(n: int) -> Points:
    i = np.arange(n) + 0.5
    z = i / n
    phi = np.pi * (1 + 5**0.5) * i
    r = np.sqrt(1 - z**2)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _candidate_axes(
    points: Points, gap: float
) -> tuple[list[NDArray[np.float64]], list[NDArray[np.float64]]]:
    """(main axes, extra axes): principal and frame axes; extra samples in degenerate spaces."""
    c = points - points.mean(axis=0)
    w, v = np.linalg.eigh(c.T @ c / len(c))
    w = w / max(w.max(), 1e-30)
    main = [v[:, i] for i in range(3)] + [np.eye(3)[i] for i in range(3)]
    extra: list[NDArray[np.float64]] = []
    close = [abs(w[i] - w[j]) < gap * max(w[i], w[j]) for i, j in ((0, 1), (1, 2))]
    if all(close):
        extra = list(_fibonacci_hemisphere(300))
    else:
        for i, j in ((0, 1), (1, 2)):
            if abs(w[i] - w[j]) < gap * max(w[i], w[j]):
                for ang in np.radians(np.arange(0.0, 180.0, 4.0)):
                    extra.append(np.cos(ang) * v[:, i] + np.sin(ang) * v[:, j])
    return main, extra


class _Scorer:
    """Nearest-neighbour figures of a surface sample against its rotated copy."""

    def __init__(self, points: Points, colors: Points | None, options: SymmetryOptions) -> None:
        rng = np.random.default_rng(options.seed)
        self.points = points
        self.colors = colors
        self.tree = cKDTree(points)
        idx = rng.choice(len(points), min(options.n_eval, len(points)), replace=False)
        self.sub_idx = idx
        self.sub = points[idx]
        self.coarse = self.sub[: min(250, len(idx))]
        dist, nn = self.tree.query(self.sub, k=2)
        self.d0 = float(dist[:, 1].mean())
        self.options = options
        self.centre = points.mean(axis=0)
        self.colour_base = (
            float(np.abs(colors[idx] - colors[nn[:, 1]]).sum(axis=1).mean())
            if colors is not None
            else 0.0
        )

    def mean_ratio(self, t: Mat4, coarse: bool = False) -> float:
        q = self.coarse if coarse else self.sub
        d, _ = self.tree.query(q @ t[:3, :3].T + t[:3, 3])
        return float(d.mean() / self.d0)

    def accepts(self, t: Mat4) -> bool:
        moved = self.sub @ t[:3, :3].T + t[:3, 3]
        d, _ = self.tree.query(moved)
        back, _ = self.tree.query((self.sub - t[:3, 3]) @ t[:3, :3])  # inverse direction
        dd = np.concatenate([d, back]) / self.d0
        o = self.options
        return bool(
            dd.mean() <= o.max_mean_ratio and (dd > o.far_ratio).mean() <= o.max_far_fraction
        )

    def colour_ratio(self, t: Mat4) -> float:
        if self.colors is None or self.colour_base <= 0:
            return 0.0
        _, nn = self.tree.query(self.sub @ t[:3, :3].T + t[:3, 3])
        diff = np.abs(self.colors[self.sub_idx] - self.colors[nn]).sum(axis=1).mean()
        return float(diff / self.colour_base)

    def snap(self, t: Mat4) -> Mat4 | None:
        """ICP-refine a candidate symmetry, snap its angle to 360°/n about the refined axis
        through the centroid, and return the better-scoring of the two if accepted."""
        refined = self.refine(t)
        ang = rotation_angle_deg(refined[:3, :3])
        if ang < DEDUPE_DEG:
            return None
        order = max(2, round(360.0 / ang))
        options = [refined]
        if abs(360.0 / order - ang) < 10.0:
            axis = _rotation_axis(refined[:3, :3])
            for sgn in (1.0, -1.0):
                cand = rotation_about(sgn * axis, 2 * np.pi / order, self.centre)
                if rotation_angle_deg(cand[:3, :3].T @ refined[:3, :3]) < 15.0:
                    options.append(cand)
        best = min(options, key=self.mean_ratio)
        return best if self.accepts(best) else None

    def refine(self, t: Mat4) -> Mat4:
        src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(self.sub))
        dst = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(self.points))
        reg = o3d.pipelines.registration.registration_icp(
            src,
            dst,
            3.0 * self.d0,
            t,
            o3d.pipelines.registration.TransformationEstimationPointToPoint(),
            o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=30),
        )
        return np.asarray(reg.transformation, dtype=np.float64).copy()


def _rotation_axis(r: NDArray[np.float64]) -> NDArray[np.float64]:
    w, v = np.linalg.eig(r)
    k = int(np.argmin(np.abs(w - 1.0)))
    a = np.real(v[:, k])
    return np.asarray(a / np.linalg.norm(a), dtype=np.float64)


def _same(a: Mat4, b: Mat4, tol_deg: float) -> bool:
    return rotation_angle_deg(a[:3, :3].T @ b[:3, :3]) < tol_deg


def _close_group(group: list[Mat4], new: Mat4, scorer: _Scorer, max_group: int) -> list[Mat4]:
    """Add ``new`` to a (closed) group and close it under composition; products are
    re-snapped and checked, so measurement drift does not accumulate."""
    group = list(group)
    frontier = [new]
    while frontier and len(group) < max_group:
        g = frontier.pop(0)
        if any(_same(g, h, DEDUPE_DEG) for h in group):
            continue
        snapped = scorer.snap(g) if g is not new else g
        if snapped is None or any(_same(snapped, h, DEDUPE_DEG) for h in group):
            continue
        group.append(snapped)
        for h in list(group):
            frontier.append(snapped @ h)
            frontier.append(h @ snapped)
    return group


def detect_symmetry(
    points: Points, colors: Points | None = None, options: SymmetryOptions = SymmetryOptions()
) -> SymmetrySpec:
    """Detect the rotational symmetry of an (N, 3) surface sample (object frame, metres).

    Candidate axes: principal axes, frame axes, and samples of any degenerate principal
    subspace (a square prism's cross-section plane, a cube's sphere). For each axis the
    180°, 120° and 90° rotations about the centroid are scored coarsely, refined by ICP and
    accepted per :class:`SymmetryOptions`; an axis whose rotations by every angle in
    ``continuous_angles_deg`` are accepted is continuous. ``colors`` ((N, 3) in [0, 1])
    only sets ``appearance_breaks``. Deterministic.
    """
    p = as_points(points)
    if len(p) < 50:
        raise InputError("symmetry detection needs at least 50 surface points")
    o = options
    scorer = _Scorer(p, colors, o)
    centre = p.mean(axis=0)
    main, extra = _candidate_axes(p, o.degenerate_gap)

    # continuous: about the main axes
    for axis in main:
        ok = all(
            scorer.accepts(rotation_about(axis, np.radians(a), centre))
            for a in o.continuous_angles_deg
        )
        if not ok:
            continue
        flips: list[Mat4] = []
        perp, other = perpendicular_pair(axis)
        for ang in np.radians(np.arange(0.0, 180.0, 15.0)):
            flip = rotation_about(np.cos(ang) * perp + np.sin(ang) * other, np.pi, centre)
            if scorer.mean_ratio(flip, coarse=True) < o.coarse_ratio:
                snapped = scorer.snap(flip)
                if snapped is not None and rotation_angle_deg(snapped[:3, :3]) > 170:
                    flips.append(snapped)
                    break
        rots = tuple([np.eye(4), *flips])
        samples = [
            rotation_about(axis, np.radians(a), centre) for a in o.continuous_angles_deg
        ] + flips
        brk = max((scorer.colour_ratio(t) for t in samples), default=0.0) > o.colour_ratio
        return SymmetrySpec("continuous", rots, np.asarray(axis, np.float64), centre, brk)

    # discrete: generators from 180°, 120°, 90° rotations about candidate axes
    cands: list[tuple[float, int, Mat4]] = []
    for i, axis in enumerate(main + extra):
        for order in (2, 3, 4) if i < len(main) else (2, 4):
            cand = rotation_about(axis, 2 * np.pi / order, centre)
            score = scorer.mean_ratio(cand, coarse=True)
            if score <= o.coarse_ratio:
                cands.append((score, order, cand))
    cands.sort(key=lambda c: c[0])
    group: list[Mat4] = [np.eye(4)]
    for _, order, cand in cands[: o.max_refinements]:
        if any(_same(cand, g, DEDUPE_DEG) for g in group):
            continue
        snapped = scorer.snap(cand)
        if snapped is None or abs(rotation_angle_deg(snapped[:3, :3]) - 360.0 / order) > 10.0:
            continue
        group = _close_group(group, snapped, scorer, o.max_group)
    group.sort(key=lambda r: rotation_angle_deg(r[:3, :3]))
    if len(group) == 1:
        return SymmetrySpec()
    brk = max(scorer.colour_ratio(t) for t in group[1:]) > o.colour_ratio
    return SymmetrySpec("discrete", tuple(group), appearance_breaks=brk)


def symmetry_axis_of(rotation: Mat4) -> NDArray[np.float64]:
    """Unit rotation axis of a 4×4 rotation (sign arbitrary)."""
    return _rotation_axis(rotation[:3, :3])


def near_symmetries(
    points: Points, spec: SymmetrySpec, options: SymmetryOptions = SymmetryOptions()
) -> list[Mat4]:
    """Rotations that *almost* map the surface onto itself but are not symmetries (a hammer
    turned over about its handle, a clamp flipped): 4×4 ``object_from_object`` about the
    centroid, whose ICP-refined mean nearest-neighbour ratio is below ``near_ratio``.

    Pose estimation tries each of them from its best candidate, because a partial view
    often cannot tell them apart at the coarse scale where RANSAC works. Deterministic.
    """
    p = as_points(points)
    scorer = _Scorer(p, None, options)
    centre = p.mean(axis=0)
    main, _ = _candidate_axes(p, options.degenerate_gap)
    group = spec.sample(8)
    out: list[Mat4] = []
    for axis in main:
        for order in (2, 4):
            cand = rotation_about(axis, 2 * np.pi / order, centre)
            if any(_same(cand, g, DEDUPE_DEG) for g in group + out):
                continue
            if scorer.mean_ratio(cand, coarse=True) > 2 * options.near_ratio:
                continue
            refined = scorer.refine(cand)
            if rotation_angle_deg(refined[:3, :3]) < DEDUPE_DEG:
                continue
            if any(_same(refined, g, DEDUPE_DEG) for g in group + out):
                continue
            if scorer.mean_ratio(refined) <= options.near_ratio:
                out.append(refined)
    return out
