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
    """(64³,) uniform values in [0, 1) from ``seed``: the value-noise lattice."""
    rng = np.random.default_rng([seed, 7919])
    return rng.random(_LATTICE**3, dtype=np.float32)


def value_noise(points: F32, cell_m: float, lattice: F32, offset: int) -> F32:
    """Trilinear value noise in [0, 1) at (N, 3) points (metres) for one cell size."""
    q = points * np.float32(1.0 / cell_m) + np.float32(offset * 17.31)
    base = np.floor(q)
    frac = q - base
    frac = frac * frac * (np.float32(3.0) - np.float32(2.0) * frac)
    i0 = base.astype(np.int64) & (_LATTICE - 1)
    i1 = (i0 + 1) & (_LATTICE - 1)
    xs = (i0[:, 0], i1[:, 0])
    ys = (i0[:, 1] * _LATTICE, i1[:, 1] * _LATTICE)
    zs = (i0[:, 2] * _LATTICE**2, i1[:, 2] * _LATTICE**2)
    fx, fy, fz = frac[:, 0], frac[:, 1], frac[:, 2]
    plane = []
    for z in zs:
        rows = []
        for y in ys:
            a = lattice[xs[0] + y + z]
            b = lattice[xs[1] + y + z]
            rows.append(a + (b - a) * fx)
        plane.append(rows[0] + (rows[1] - rows[0]) * fy)
    out: F32 = plane[0] + (plane[1] - plane[0]) * fz
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
            if footprint_m is None:
                shade += weight * (value_noise(p, size, lattice, k) - np.float32(0.5))
                continue
            fade = np.clip(np.float32(size) / footprint_m - np.float32(1.0), 0.0, 1.0)
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
