"""Streaming voxel averaging: chunks of points in, one mean point and mean colour per
occupied voxel out, in memory proportional to the occupied voxels (never the input)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from workers.pipeline.errors import InputError, ShapeError
from workers.pipeline.geometry import as_points

FloatArray = NDArray[np.float64]
ColorArray = NDArray[np.uint8]


class ScanTooDense(InputError):
    """The scan, averaged on the voxel asked for, would not fit the memory allowed."""

    code = "ScanTooDense"


_BITS = 21  # per axis: ±2^20 voxels (±2.6 km at 2.5 mm)
_OFFSET = 1 << (_BITS - 1)


class VoxelGrid:
    """Sums of points and colours per ``voxel_m`` cube (grid at the origin). Chunks' sums
    are merged once the pending voxels outnumber ``merge_every`` and the voxels merged so
    far (so each voxel is re-sorted O(log n) times, not once per chunk). Colours count only
    while every chunk has them."""

    def __init__(
        self, voxel_m: float, merge_every: int = 4_000_000, max_voxels: int | None = None
    ) -> None:
        if not (np.isfinite(voxel_m) and voxel_m > 0):
            raise InputError(f"voxel size must be > 0 metres, got {voxel_m}")
        self.voxel_m = float(voxel_m)
        self.merge_every = merge_every
        self.max_voxels = max_voxels
        self.colored = True
        self.n_in = 0
        self._parts: list[tuple[NDArray[np.int64], FloatArray]] = []
        self._pending = 0
        self._merged = 0

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
        if self._pending > max(self.merge_every, self._merged) and len(self._parts) > 1:
            self._merge()

    def _merge(self) -> None:
        keys = np.concatenate([k for k, _ in self._parts])
        values = np.concatenate([v for _, v in self._parts])
        self._parts = []
        self._pending = 0
        self._push(keys, values)
        self._pending = 0
        self._merged = len(self._parts[0][0])
        if self.max_voxels is not None and self._merged > self.max_voxels:
            raise ScanTooDense(
                f"the scan averages to more than {self.max_voxels} voxels of "
                f"{self.voxel_m * 1000:g} mm (about {64 * self.max_voxels / 1e6:.0f} MB); "
                "give the environment a coarser reconstruct voxel_size_m or crop the scan"
            )

    def result(self) -> tuple[FloatArray, ColorArray | None]:
        """((M, 3) mean points in metres, (M, 3) uint8 mean colours or None). Raises
        ScanTooDense past ``max_voxels``."""
        if not self._parts:
            return np.zeros((0, 3)), None
        if len(self._parts) > 1 or self._merged == 0:
            self._merge()
        _, sums = self._parts[0]
        counts = sums[:, 6:7]
        points = sums[:, :3] / counts
        if not self.colored:
            return points, None
        colors = np.clip(np.rint(sums[:, 3:6] / counts), 0, 255).astype(np.uint8)
        return points, colors
