"""The support surfaces of a snapshot: floor, table tops, shelf boards.

Horizontal planes of the environment frame (z up, metres): peaks of the height histogram
whose slab of points covers a wide area once thin lines (walls seen edge-on in the raster)
are opened away; the wide patches of one slab are one support. Each support has a
least-squares plane refitted on its own points, the robust spread of those points about
it (the cloud's noise there), and a footprint raster whose object-sized holes are filled,
since nothing sees the floor beneath an object.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from workers.pipeline.geometry import Points
from workers.pipeline.inventory.options import InventoryOptions

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True, eq=False)
class Support:
    """One horizontal support surface.

    ``plane`` (4,) ``[n, d]`` with unit ``n`` pointing up (n_z > 0): height above it is
    ``n·p + d`` metres; ``noise_m`` the robust sigma (1.4826 × MAD) of its points about the
    plane; ``footprint`` (H, W) cells of ``cell_m`` from ``origin_xy`` (2,) metres, True
    where the support is (holes filled); ``n_points`` its points; ``area_m2`` its footprint.
    """

    name: str
    plane: FloatArray
    noise_m: float
    origin_xy: FloatArray
    cell_m: float
    footprint: BoolArray
    n_points: int

    @property
    def height_m(self) -> float:
        """Height of the plane at the footprint's centroid, metres."""
        rows, cols = np.nonzero(self.footprint)
        centre = self.origin_xy + self.cell_m * (np.array([cols.mean(), rows.mean()]) + 0.5)
        n, d = self.plane[:3], self.plane[3]
        return float(-(n[0] * centre[0] + n[1] * centre[1] + d) / n[2])

    @property
    def area_m2(self) -> float:
        return float(self.footprint.sum() * self.cell_m**2)

    def height_above(self, points_env: Points) -> FloatArray:
        """(N,) signed height of (N, 3) points above the plane, metres."""
        return np.asarray(points_env @ self.plane[:3] + self.plane[3], dtype=np.float64)

    def covers(self, points_env: Points) -> BoolArray:
        """(N,) whether each point's (x, y) lies over the footprint."""
        ij = np.floor((points_env[:, :2] - self.origin_xy) / self.cell_m).astype(np.int64)
        h, w = self.footprint.shape
        inside = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
        out = np.zeros(len(points_env), dtype=bool)
        out[inside] = self.footprint[ij[inside, 1], ij[inside, 0]]
        return out

    def to_json(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "plane": [float(v) for v in self.plane],
            "height_m": round(self.height_m, 5),
            "noise_m": round(self.noise_m, 5),
            "area_m2": round(self.area_m2, 4),
            "n_points": self.n_points,
        }


def _fit_plane(points: Points) -> tuple[FloatArray, FloatArray]:
    """Least-squares plane ``[n, d]`` (n up) of (N ≥ 3, 3) points and their residuals."""
    centre = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centre, full_matrices=False)
    n = vt[2] if vt[2, 2] >= 0 else -vt[2]
    plane = np.append(n, -float(n @ centre))
    return plane, points @ n + plane[3]


def _level_plane(points: Points) -> tuple[FloatArray, FloatArray]:
    """The horizontal plane ``[0, 0, 1, −median z]`` of (N ≥ 1, 3) points and residuals."""
    plane = np.array([0.0, 0.0, 1.0, -float(np.median(points[:, 2]))])
    return plane, points[:, 2] + plane[3]


def _robust_plane(
    points: Points, level: bool, rounds: int = 3
) -> tuple[FloatArray, float, BoolArray]:
    """A plane (horizontal when ``level``) refitted on the points within 3 robust sigmas of
    the previous fit; returns the plane, the sigma and the inlier mask."""
    fit = _level_plane if level else _fit_plane
    keep = np.ones(len(points), dtype=bool)
    plane, resid = fit(points)
    sigma = 0.0
    for _ in range(rounds):
        sigma = max(1.4826 * float(np.median(np.abs(resid - np.median(resid)))), 1e-4)
        keep = np.abs(resid) <= 3.0 * sigma
        if keep.sum() < 3:
            break
        plane, _ = fit(points[keep])
        resid = points @ plane[:3] + plane[3]
    return plane, sigma, keep


def _peaks(z: FloatArray, options: InventoryOptions) -> list[float]:
    """Heights of the histogram's local maxima, highest count first, at least two slabs
    apart."""
    lo, hi = float(z.min()), float(z.max())
    bins = max(int(np.ceil((hi - lo) / options.support_bin_m)), 1)
    counts, edges = np.histogram(z, bins=bins, range=(lo, lo + bins * options.support_bin_m))
    centres = (edges[:-1] + edges[1:]) / 2
    padded = np.concatenate([[-1], counts, [-1]])
    is_peak = (counts >= padded[:-2]) & (counts >= padded[2:]) & (counts > 0)
    order = np.flatnonzero(is_peak)[np.argsort(-counts[is_peak], kind="stable")]
    chosen: list[float] = []
    for i in order[: options.max_support_peaks]:
        if all(abs(centres[i] - c) > 2 * options.support_slab_m for c in chosen):
            chosen.append(float(centres[i]))
    return chosen


def _flat_columns(points_env: Points, lo_xy: FloatArray, options: InventoryOptions) -> BoolArray:
    """(N,) whether each point's raster column holds at most ``column_max_bins`` occupied
    height bins: not a wall, a furniture side or an object's flank (they span many bins
    and drown a small table top in the height histogram)."""
    cell = options.support_cell_m
    ij = np.floor((points_env[:, :2] - lo_xy) / cell).astype(np.int64)
    column = ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1]
    k = np.floor(points_env[:, 2] / options.support_bin_m).astype(np.int64)
    k -= k.min()
    span = int(k.max()) + 1
    occupied = np.unique(column * span + k)  # one entry per (column, height bin)
    cols, n_bins = np.unique(occupied // span, return_counts=True)
    return n_bins[np.searchsorted(cols, column)] <= options.column_max_bins


def _slab_support(
    points_env: Points,
    in_slab: NDArray[np.int64],
    ij: NDArray[np.int64],
    regions: list[BoolArray],
    origin_xy: FloatArray,
    close_cells: int,
    options: InventoryOptions,
) -> Support | None:
    """One support from the wide raster ``regions`` of one height slab (``in_slab`` point
    indices, ``ij`` their raster cells from ``origin_xy``): patches of one level (a floor
    that shelves, walls or sparse far strips cut into pieces) share one plane and the
    noise of all their points; a small patch alone would mostly hold the objects standing
    on it and take their height for noise. None when the plane is steeper than about 14°."""
    in_regions = np.any(np.stack(regions), axis=0)
    mine = in_slab[in_regions[ij[:, 1], ij[:, 0]]]
    plane, sigma, keep = _robust_plane(points_env[mine], options.level_supports)
    if plane[2] < 0.97:  # a ramp or a tilted board, not a support
        return None
    footprint = np.zeros_like(in_regions)
    for region in regions:
        closed = ndimage.binary_closing(
            region, structure=np.ones((3, 3)), iterations=close_cells, border_value=0
        )
        footprint |= ndimage.binary_fill_holes(closed | region)
    return Support(
        name="",
        plane=plane,
        noise_m=sigma,
        origin_xy=origin_xy.astype(np.float64),
        cell_m=options.support_cell_m,
        footprint=np.asarray(footprint, dtype=bool),
        n_points=int(keep.sum()),
    )


def find_supports(
    points_env: Points, max_diameter_m: float, options: InventoryOptions
) -> list[Support]:
    """The horizontal support surfaces of an (N, 3) cloud (environment frame, z up,
    metres), lowest first (the floor, then table tops and shelf boards). ``max_diameter_m``
    the largest library object's diameter (the footprint's holes up to about it are
    filled; a support is wider than ``support_area_diameters`` × its square). Returns []
    when no slab covers ``min_support_area_m2``."""
    if len(points_env) == 0:
        return []
    cell = options.support_cell_m
    lo_xy = points_env[:, :2].min(axis=0) - cell
    flat = _flat_columns(points_env, lo_xy, options)
    z = np.where(flat, points_env[:, 2], np.nan)
    shape_wh = np.ceil((points_env[:, :2].max(axis=0) + cell - lo_xy) / cell).astype(int) + 1
    close_cells = max(int(np.ceil(options.footprint_close_diameters * max_diameter_m / cell)), 1)
    opening = options.support_opening_cells
    min_area = max(options.min_support_area_m2, options.support_area_diameters * max_diameter_m**2)
    found: list[Support] = []
    for peak in _peaks(z[flat], options):
        in_slab = np.flatnonzero(np.abs(z - peak) <= options.support_slab_m)
        if len(in_slab) < 3:
            continue
        ij = np.floor((points_env[in_slab, :2] - lo_xy) / cell).astype(np.int64)
        raster = np.zeros((shape_wh[1], shape_wh[0]), dtype=bool)
        raster[ij[:, 1], ij[:, 0]] = True
        # closing first: a slab sampled sparser than the cell, or with holes, is a surface
        solid = raster
        if options.support_closing_cells > 0:
            solid = ndimage.binary_closing(raster, iterations=options.support_closing_cells)
        if opening > 0:
            solid = ndimage.binary_opening(solid, iterations=opening)
        labels, n = ndimage.label(solid, structure=np.ones((3, 3)))
        wide = [
            labels == label
            for label in range(1, n + 1)
            if (labels == label).sum() * cell * cell >= min_area
        ]
        if wide:
            support = _slab_support(points_env, in_slab, ij, wide, lo_xy, close_cells, options)
            if support is not None:
                found.append(support)
    found.sort(key=lambda s: s.height_m)
    if not found:
        return []
    # the floor: the widest support within two slabs of the lowest (a low platform or a
    # sunken patch beside the floor is a support of its own)
    lowest = [s for s in found if s.height_m <= found[0].height_m + 2 * options.support_slab_m]
    floor = max(lowest, key=lambda s: s.area_m2)
    named = []
    others = 0
    for s in found:
        others += s is not floor
        name = "floor" if s is floor else f"surface_{others}"
        named.append(
            Support(name, s.plane, s.noise_m, s.origin_xy, s.cell_m, s.footprint, s.n_points)
        )
    return named


def standing_heights(
    points_env: Points, supports: list[Support]
) -> tuple[FloatArray, NDArray[np.int64]]:
    """For each of (N, 3) points: its height above the highest support beneath it (whose
    footprint covers it and whose plane is below it), and that support's index; NaN and
    −1 where no support is beneath."""
    heights = np.full(len(points_env), np.nan)
    owner = np.full(len(points_env), -1, dtype=np.int64)
    for i, support in enumerate(supports):  # lowest first: a higher one beneath wins
        h = support.height_above(points_env)
        under = support.covers(points_env) & (h > -3.0 * max(support.noise_m, 1e-3))
        heights[under] = h[under]
        owner[under] = i
    return heights, owner
