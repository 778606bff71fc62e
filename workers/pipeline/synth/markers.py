"""The printed reference: ArUco markers (DICT_4X4_50) lying flat on the floor.

Marker frame (docs/contract.md): origin at the marker centre, x right, y up, z out of the printed
face; corners (−s/2, s/2, 0), (s/2, s/2, 0), (s/2, −s/2, 0), (−s/2, −s/2, 0). On the floor
the printed face looks up, so marker z is environment z.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from workers.pipeline.geometry import Mat4, make_rigid
from workers.pipeline.synth.options import RoomOptions
from workers.pipeline.synth.texture import F32

DICTIONARY = "DICT_4X4_50"
PAPER = np.float32(0.93)
INK = np.float32(0.06)
_MARKER_PX = 6 * 24  # 4×4 bits + black border, 24 texels per cell


def rot_z(yaw_rad: float) -> NDArray[np.float64]:
    """(3, 3) rotation about +z by ``yaw_rad`` radians."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    return np.asarray([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def marker_corners_m(size_m: float) -> NDArray[np.float64]:
    """(4, 3) corners in the marker frame, in OpenCV's detection order."""
    h = size_m / 2.0
    return np.asarray([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


@dataclass(frozen=True)
class MarkerSheet:
    """Markers on the floor: ``env_from_marker`` per id, ``size_m`` the black square's side,
    ``margin_m`` the white paper border around it."""

    env_from_marker: dict[int, Mat4]
    size_m: float
    margin_m: float

    @cached_property
    def _images(self) -> dict[int, F32]:
        aruco = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
        out = {}
        for marker_id in self.env_from_marker:
            img = cv2.aruco.generateImageMarker(aruco, marker_id, _MARKER_PX)
            out[marker_id] = np.where(img > 127, PAPER, INK).astype(np.float32)
        return out

    def tile_radius_m(self) -> float:
        """Radius of the circle around a marker centre that holds its paper tile."""
        return float(np.sqrt(2.0) * (self.size_m / 2.0 + self.margin_m))

    @cached_property
    def _coarse(self) -> tuple[NDArray[np.float64], float, NDArray[np.bool_]]:
        """(origin xy, cell size, occupancy grid): cells that may hold marker paper."""
        cell = 0.02
        r = self.tile_radius_m() + cell
        centres = np.asarray([pose[:2, 3] for pose in self.env_from_marker.values()])
        lo = centres.min(axis=0) - r
        shape = np.ceil((centres.max(axis=0) + r - lo) / cell).astype(int) + 1
        ij = np.stack(np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij"), -1)
        xy = lo + (ij + 0.5) * cell
        near = np.zeros(tuple(shape), bool)
        for c in centres:
            near |= np.linalg.norm(xy - c, axis=-1) <= r
        return lo, cell, near

    def albedo(self, points_env: F32) -> tuple[F32, NDArray[np.bool_]]:
        """Grey albedo (N,) and on-paper mask (N,) of (N, 3) floor points (environment frame)."""
        out = np.zeros(len(points_env), np.float32)
        on_paper = np.zeros(len(points_env), bool)
        lo, cell, near = self._coarse
        ij = np.floor((points_env[:, :2] - lo) / cell).astype(np.int64)
        inside_grid = np.all((ij >= 0) & (ij < near.shape), axis=1)
        candidates = np.flatnonzero(inside_grid)
        candidates = candidates[near[ij[candidates, 0], ij[candidates, 1]]]
        if len(candidates) == 0:
            return out, on_paper
        xy = points_env[candidates, :2].astype(np.float64)
        half, paper = self.size_m / 2.0, self.size_m / 2.0 + self.margin_m
        for marker_id, env_from_marker in self.env_from_marker.items():
            local = (xy - env_from_marker[:2, 3]) @ np.ascontiguousarray(env_from_marker[:2, :2])
            inside = np.all(np.abs(local) <= paper, axis=1)
            if not inside.any():
                continue
            idx = candidates[inside]
            on_paper[idx] = True
            lx, ly = local[inside, 0], local[inside, 1]
            value = np.full(len(lx), PAPER, np.float32)
            printed = (np.abs(lx) < half) & (np.abs(ly) < half)
            col = ((lx[printed] + half) / self.size_m * _MARKER_PX).astype(np.int64)
            row = ((half - ly[printed]) / self.size_m * _MARKER_PX).astype(np.int64)
            img = self._images[marker_id]
            value[printed] = img[np.clip(row, 0, _MARKER_PX - 1), np.clip(col, 0, _MARKER_PX - 1)]
            out[idx] = value
        return out, on_paper

    def reference(self) -> dict[str, Any]:
        """The environment ``reference`` JSON of docs/contract.md."""
        return {
            "markers": {
                "dictionary": DICTIONARY,
                "size": self.size_m,
                "poses": {str(k): v.tolist() for k, v in sorted(self.env_from_marker.items())},
            }
        }


def marker_sheet(room: RoomOptions) -> MarkerSheet:
    """Markers evenly on a ring of ``room.marker_ring_m`` around the origin, each turned
    differently; the layout depends on the options only (a site keeps its reference)."""
    poses: dict[int, Mat4] = {}
    n = len(room.marker_ids)
    for k, marker_id in enumerate(room.marker_ids):
        angle = 2.0 * np.pi * (k + 0.5) / n
        centre = room.marker_ring_m * np.asarray([np.cos(angle), np.sin(angle), 0.0])
        poses[marker_id] = make_rigid(rot_z(angle + 0.6 * k), centre)
    return MarkerSheet(poses, room.marker_size_m, room.marker_margin_m)
