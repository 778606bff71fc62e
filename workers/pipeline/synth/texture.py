"""View-consistent solid textures: colours evaluated from 3D positions, never per view.

A surface point always gets the same colour whatever the camera, so features match across
views. Static surfaces are evaluated in the environment frame, objects in their own frame
(a moved object keeps its look).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

F32 = NDArray[np.float32]

_LATTICE = 64
_OCTAVES_M: tuple[tuple[float, float], ...] = (
    # (cell size in metres, amplitude): broad patches, then fine detail for feature matching
    (0.60, 0.30),
    (0.25, 0.22),
    (0.11, 0.18),
    (0.05, 0.16),
    (0.022, 0.16),
    (0.010, 0.14),
    (0.005, 0.10),
)


@lru_cache(maxsize=64)
def _lattice(seed: int) -> F32:
    """Value-noise lattice of ``seed``: 64³ uniform values in [0, 1), stored wrap-padded to
    65³ and flattened (index x + 65·y + 65²·z) so that a cell's 8 corners are fixed offsets."""
    rng = np.random.default_rng([seed, 7919])
    cube = rng.random((_LATTICE,) * 3, dtype=np.float32)
    padded: F32 = np.pad(cube, ((0, 1), (0, 1), (0, 1)), mode="wrap").reshape(-1)
    return padded


_ROW, _SLAB = _LATTICE + 1, (_LATTICE + 1) ** 2
_CORNERS = np.asarray(
    [0, 1, _ROW, _ROW + 1, _SLAB, _SLAB + 1, _SLAB + _ROW, _SLAB + _ROW + 1], np.int32
)[:, None]


def value_noise(points: F32, cell_m: float, lattice: F32, offset: int) -> F32:
    """Value noise in [0, 1) at (N, 3) points (metres): smoothstep-trilinear interpolation
    of the lattice at cells of ``cell_m``; ``offset`` shifts to an unrelated lattice region."""
    q = points * np.float32(1.0 / cell_m) + np.float32(offset * 17.31)
    base = np.floor(q)
    frac = q - base
    frac *= frac * (np.float32(3.0) - np.float32(2.0) * frac)
    cell = base.astype(np.int32)
    cell &= _LATTICE - 1
    index = cell[:, 0] + _ROW * cell[:, 1] + _SLAB * cell[:, 2]
    fx, fy, fz = np.ascontiguousarray(frac.T)
    c = np.take(lattice, index[None, :] + _CORNERS)  # (8, N): x fastest, then y, then z
    x = c[0::2] + (c[1::2] - c[0::2]) * fx  # (4, N)
    y = x[0::2] + (x[1::2] - x[0::2]) * fy  # (2, N)
    out: F32 = y[0] + (y[1] - y[0]) * fz
    return out


@dataclass(frozen=True)
class SolidTexture:
    """A two-colour solid texture: low-frequency colour mix × multi-octave brightness.

    ``colour_a``/``colour_b`` are RGB in [0, 1]; ``seed`` picks the lattice; ``scale``
    multiplies every cell size (larger = coarser).
    """

    colour_a: tuple[float, float, float]
    colour_b: tuple[float, float, float]
    seed: int
    scale: float = 1.0
    contrast: float = 0.9

    def colours(self, points: NDArray[np.floating], footprint_m: F32 | None = None) -> F32:
        """RGB in [0, 1], (N, 3) float32, at (N, 3) points in the texture's frame (metres).

        ``footprint_m`` (N,), the size of a pixel on the surface, fades out octaves finer
        than about two pixels (as a camera's pixel integration would) and skips their cost.
        """
        p = np.ascontiguousarray(points, dtype=np.float32)
        lattice = _lattice(self.seed)
        total = sum(a for _, a in _OCTAVES_M)
        shade = np.full(len(p), 0.5, np.float32)
        for k, (cell, amp) in enumerate(_OCTAVES_M):
            size = cell * self.scale
            weight = np.float32(amp / total)
            fade = None
            if footprint_m is not None:
                fade = np.clip(np.float32(size) / footprint_m - np.float32(1.0), 0.0, 1.0)
            if fade is None or fade.min() >= 1.0:
                shade += weight * (value_noise(p, size, lattice, k) - np.float32(0.5))
                continue
            live = np.flatnonzero(fade > 0)
            if len(live):
                noise = value_noise(p[live], size, lattice, k) - np.float32(0.5)
                shade[live] += weight * fade[live] * noise
        mix = value_noise(p, 0.35 * self.scale, lattice, 11)
        mix = np.clip((mix - np.float32(0.3)) * np.float32(2.5), 0.0, 1.0)[:, None]
        a = np.asarray(self.colour_a, np.float32)
        b = np.asarray(self.colour_b, np.float32)
        base = a + (b - a) * mix
        gain = np.float32(1.0) + np.float32(2.0 * self.contrast) * (shade - np.float32(0.5))
        out: F32 = np.clip(base * gain[:, None], 0.0, 1.0)
        return out
