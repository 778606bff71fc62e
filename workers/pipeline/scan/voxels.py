"""Streaming voxel averaging: chunks of points in, one mean point and mean colour per
occupied voxel out, in memory proportional to the occupied voxels (never the input)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from workers.pipeline.errors import InputError, ShapeError
from workers.pipeline.geometry import as_points

FloatArray = NDArray[np.float64]
ColorArray = NDArray[np.uint8]

_BITS = 21  # per axis: ±2^20 voxels (±2.6 km at 2.5 mm)
_OFFSET = 1 << (_BITS - 1)


class VoxelGrid:
    """Sums of points and colours per ``voxel_m`` cube (grid at the origin), merged every
    ``merge_every`` pending voxels. Colours count only while every chunk has them."""

    def __init__(self, voxel_m: float, merge_every: int = 4_000_000) -> None:
        if not (np.isfinite(voxel_m) and voxel_m > 0):
            raise InputError(f"voxel size must be > 0 metres, got {voxel_m}")
        self.voxel_m = float(voxel_m)
        self.merge_every = merge_every
        self.colored = True
        self.n_in = 0
        self._parts: list[tuple[NDArray[np.int64], FloatArray]] = []
        self._pending = 0

    def add(self, points_m: FloatArray, colors: ColorArray | None) -> None:
        """Add (N, 3) points in metres and their (N, 3) uint8 colours (or None)."""
        pts = as_points(points_m, "points_m")
        finite = np.all(np.isfinite(pts), axis=1)
        pts = pts[finite]
        if colors is None:
            self.colored = False
            cols = np.zeros((len(pts), 3))
        else:
            if len(colors) != len(finite):
                raise ShapeError(f"colors must be ({len(finite)}, 3), got {np.shape(colors)}")
            cols = np.asarray(colors, np.float64)[finite]
        self.n_in += len(pts)
        if len(pts) == 0:
            return
        keys = np.floor(pts / self.voxel_m).astype(np.int64)
        if np.abs(keys).max() >= _OFFSET:
            raise InputError(
                f"the scan reaches {np.abs(pts).max():.0f} m from its origin; at most "
                f"{_OFFSET * self.voxel_m:.0f} m is supported"
            )
        packed = ((keys[:, 0] + _OFFSET) << (2 * _BITS)) | ((keys[:, 1] + _OFFSET) << _BITS)
        packed |= keys[:, 2] + _OFFSET
        # columns: x, y, z sums, r, g, b sums, count
        values = np.column_stack([pts, cols, np.ones(len(pts))])
        self._push(packed, values)

    def _push(self, packed: NDArray[np.int64], values: FloatArray) -> None:
        uniq, inverse = np.unique(packed, return_inverse=True)
        sums = np.stack(
            [np.bincount(inverse, weights=values[:, j], minlength=len(uniq)) for j in range(7)],
            axis=1,
        )
        self._parts.append((np.asarray(uniq, np.int64), np.asarray(sums, np.float64)))
        self._pending += len(uniq)
        if self._pending > self.merge_every and len(self._parts) > 1:
            self._merge()

    def _merge(self) -> None:
        keys = np.concatenate([k for k, _ in self._parts])
        values = np.concatenate([v for _, v in self._parts])
        self._parts = []
        self._pending = 0
        self._push(keys, values)
        self._pending = 0

    def result(self) -> tuple[FloatArray, ColorArray | None]:
        """((M, 3) mean points in metres, (M, 3) uint8 mean colours or None)."""
        if not self._parts:
            return np.zeros((0, 3)), None
        if len(self._parts) > 1:
            self._merge()
        _, sums = self._parts[0]
        counts = sums[:, 6:7]
        points = sums[:, :3] / counts
        if not self.colored:
            return points, None
        colors = np.clip(np.rint(sums[:, 3:6] / counts), 0, 255).astype(np.uint8)
        return points, colors
