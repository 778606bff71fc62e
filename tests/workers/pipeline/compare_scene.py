"""Synthetic scenes for the compare tests (no tests here): boxes on a floor, pinhole cameras
looking at them, and YOLO detections made by projecting the true objects.

Units metres, environment frame z up; cameras OpenCV axes. Clouds are *randomly* sampled
(not on a grid) with a different seed per capture, as two reconstructions would be.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from workers.pipeline.compare import (
    PRESETS,
    Camera,
    CaptureData,
    CompareOptions,
    CompareResult,
    TwinInstance,
    compare_snapshots,
)
from workers.pipeline.geometry import make_rigid

DENSITY = 4000.0  # points per m² (median spacing ≈ 8 mm)
NOISE = 0.001  # m
CLASSES = ["crate", "bin", "cart"]


@dataclass(frozen=True)
class Obj:
    """A library object instance: class id, and one or more boxes (centre xy, size) on
    the floor; a "cart" is two boxes with a gap (to test merging)."""

    class_id: int
    xy: tuple[float, float]
    parts: tuple[tuple[tuple[float, float], tuple[float, float, float]], ...]

    def boxes(self) -> list[tuple[NDArray[np.float64], NDArray[np.float64]]]:
        """(centre (3,), size (3,)) of each part in the environment frame."""
        out = []
        for (dx, dy), size in self.parts:
            c = np.array([self.xy[0] + dx, self.xy[1] + dy, size[2] / 2])
            out.append((c, np.array(size)))
        return out

    def corners(self) -> NDArray[np.float64]:
        pts = []
        for c, s in self.boxes():
            for sx in (-1, 1):
                for sy in (-1, 1):
                    for sz in (-1, 1):
                        pts.append(c + 0.5 * s * np.array([sx, sy, sz]))
        return np.array(pts)

    @property
    def centroid(self) -> NDArray[np.float64]:
        return np.asarray(np.mean([c for c, _ in self.boxes()], axis=0))


def crate(x: float, y: float) -> Obj:
    return Obj(0, (x, y), (((0.0, 0.0), (0.4, 0.3, 0.3)),))


def bin_(x: float, y: float) -> Obj:
    return Obj(1, (x, y), (((0.0, 0.0), (0.25, 0.25, 0.5)),))


def cart(x: float, y: float) -> Obj:
    return Obj(1 + 1, (x, y), (((-0.225, 0.0), (0.3, 0.3, 0.3)), ((0.225, 0.0), (0.3, 0.3, 0.3))))


DIAMETERS = {
    "crate": float(np.linalg.norm([0.4, 0.3, 0.3])),
    "bin": float(np.linalg.norm([0.25, 0.25, 0.5])),
    "cart": float(np.linalg.norm([0.75, 0.3, 0.3])),
}


def _sample_rect(
    rng: np.random.Generator,
    origin: NDArray[np.float64],
    u: NDArray[np.float64],
    v: NDArray[np.float64],
) -> NDArray[np.float64]:
    area = float(np.linalg.norm(np.cross(u, v)))
    n = rng.poisson(DENSITY * area)
    a, b = rng.random((n, 1)), rng.random((n, 1))
    return origin + a * u + b * v


def sample_box(
    rng: np.random.Generator, c: NDArray[np.float64], s: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Points on the 5 visible faces (not the bottom) of an axis-aligned box."""
    h = s / 2
    ex, ey, ez = np.array([s[0], 0, 0]), np.array([0, s[1], 0]), np.array([0, 0, s[2]])
    lo = c - h
    faces = [
        (lo + ez, ex, ey),  # top
        (lo, ex, ez),
        (lo + ey, ex, ez),
        (lo, ey, ez),
        (lo + ex, ey, ez),
    ]
    return np.concatenate([_sample_rect(rng, o, a, b) for o, a, b in faces])


def sample_floor(
    rng: np.random.Generator,
    objs: Sequence[Obj],
    half: float = 2.0,
    x_range: tuple[float, float] | None = None,
) -> NDArray[np.float64]:
    """Floor points on [-half, half]², minus the footprints of ``objs`` (not seen)."""
    pts = _sample_rect(
        rng, np.array([-half, -half, 0.0]), np.array([2 * half, 0, 0]), np.array([0, 2 * half, 0])
    )
    keep = np.ones(len(pts), dtype=bool)
    for o in objs:
        for c, s in o.boxes():
            inside = (np.abs(pts[:, 0] - c[0]) < s[0] / 2) & (np.abs(pts[:, 1] - c[1]) < s[1] / 2)
            keep &= ~inside
    pts = pts[keep]
    if x_range is not None:
        pts = pts[(pts[:, 0] >= x_range[0]) & (pts[:, 0] <= x_range[1])]
    return pts


def look_at(eye: Sequence[float], target: Sequence[float]) -> NDArray[np.float64]:
    """cam_from_env for a camera at ``eye`` looking at ``target`` (z up world, OpenCV cam)."""
    e, t = np.asarray(eye, float), np.asarray(target, float)
    z = t - e
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    env_from_cam = make_rigid(np.column_stack([x, y, z]), e)
    r = env_from_cam[:3, :3]
    return make_rigid(r.T, -r.T @ e)


def ring_cameras(
    n: int = 8,
    radius: float = 3.0,
    height: float = 2.0,
    target: Sequence[float] = (0, 0, 0.1),
    prefix: str = "img",
    width: int = 640,
    height_px: int = 480,
    f: float = 450.0,
) -> list[Camera]:
    k = np.array([[f, 0, width / 2], [0, f, height_px / 2], [0, 0, 1.0]])
    cams = []
    for i in range(n):
        a = 2 * np.pi * i / n
        eye = (target[0] + radius * np.cos(a), target[1] + radius * np.sin(a), height)
        cams.append(Camera(f"{prefix}{i:02d}", k, width, height_px, look_at(eye, target)))
    return cams


def detections(cameras: Sequence[Camera], objs: Sequence[Obj]) -> dict[str, NDArray[np.float64]]:
    """YOLO rows per image: the box of each object's projected corners, clipped to the image,
    kept when its centre is in view and it is in front of the camera."""
    out: dict[str, NDArray[np.float64]] = {}
    for cam in cameras:
        rows = []
        for o in objs:
            p = o.corners() @ cam.cam_from_env[:3, :3].T + cam.cam_from_env[:3, 3]
            if np.any(p[:, 2] <= 0.05):
                continue
            uv = (p[:, :2] / p[:, 2:]) @ cam.k[:2, :2].T + cam.k[:2, 2]
            x1, y1 = np.clip(uv.min(axis=0), 0, [cam.width, cam.height])
            x2, y2 = np.clip(uv.max(axis=0), 0, [cam.width, cam.height])
            if x2 - x1 < 4 or y2 - y1 < 4:
                continue
            rows.append(
                [
                    o.class_id,
                    (x1 + x2) / 2 / cam.width,
                    (y1 + y2) / 2 / cam.height,
                    (x2 - x1) / cam.width,
                    (y2 - y1) / cam.height,
                    0.9,
                ]
            )
        out[cam.name] = np.array(rows).reshape(-1, 6)
    return out


def capture(
    objs: Sequence[Obj],
    cameras: Sequence[Camera],
    seed: int,
    x_range: tuple[float, float] | None = None,
    extra: NDArray[np.float64] | None = None,
) -> CaptureData:
    """A capture of ``objs`` on the floor seen by ``cameras`` (cloud seeded by ``seed``)."""
    rng = np.random.default_rng(seed)
    parts = [sample_floor(rng, objs, x_range=x_range)]
    for o in objs:
        for c, s in o.boxes():
            parts.append(sample_box(rng, c, s))
    if extra is not None:
        parts.append(extra)
    pts = np.concatenate(parts)
    if x_range is not None:
        pts = pts[(pts[:, 0] >= x_range[0]) & (pts[:, 0] <= x_range[1])]
    pts = pts + rng.normal(0, NOISE, pts.shape)
    return CaptureData(points_env=pts, cameras=tuple(cameras), detections=detections(cameras, objs))


def twin_of(objs: Sequence[Obj], ids: Sequence[str]) -> list[TwinInstance]:
    return [
        TwinInstance(i, CLASSES[o.class_id], make_rigid(np.eye(3), o.centroid), o.centroid)
        for o, i in zip(objs, ids, strict=True)
    ]


class Counter:
    """Deterministic id factory: "id-1", "id-2", ..."""

    def __init__(self, prefix: str = "id") -> None:
        self.prefix, self.n = prefix, 0

    def __call__(self) -> str:
        self.n += 1
        return f"{self.prefix}-{self.n}"


# the shared scene of the change tests: a crate and a bin seen by a ring of cameras
CAMS = ring_cameras()
BASE = [crate(-0.8, 0.5), bin_(0.7, -0.6)]
TWIN = twin_of(BASE, ["crate-1", "bin-1"])


def run(
    before: CaptureData,
    objs: Sequence[Obj],
    twin: Sequence[TwinInstance] = TWIN,
    options: CompareOptions = PRESETS["default"],
) -> CompareResult:
    """Compare ``before`` with a capture of ``objs`` (seed 2) by the ring cameras."""
    after = capture(objs, CAMS, seed=2)
    return compare_snapshots(before, after, twin, CLASSES, DIAMETERS, options, new_id=Counter())
