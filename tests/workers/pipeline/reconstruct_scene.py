"""Test helper, imported by the reconstruct tests (no tests of its own): a textured floor
plane with ArUco markers, imaged by a ring of pinhole cameras. A plane is rendered exactly by
a homography (cv2.warpPerspective), so no renderer is needed. Env frame: z up, floor at
z = 0; texture covers [-0.5, 0.5]² m.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

TEX_PX_PER_M = 2000
HALF_M = 0.5
W, H, F = 640, 480, 560.0


def k_matrix() -> NDArray[np.float64]:
    return np.array([[F, 0, (W - 1) / 2], [0, F, (H - 1) / 2], [0, 0, 1.0]])


def look_at(eye: NDArray[np.float64], target: NDArray[np.float64]) -> NDArray[np.float64]:
    """env_from_cam, OpenCV axes, env z up."""
    fwd = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    m = np.eye(4)
    m[:3, :3] = np.stack([right, down, fwd], axis=1)
    m[:3, 3] = eye
    return m


def marker_poses(size: float) -> dict[int, NDArray[np.float64]]:
    """env_from_marker for 4 flat markers (marker z = env z), yawed differently."""
    out = {}
    for mid, (x, y, yaw) in enumerate(
        [(-0.3, -0.3, 0.0), (0.3, -0.3, 0.5), (0.3, 0.3, 1.2), (-0.3, 0.3, 2.0)]
    ):
        m = np.eye(4)
        c, s = np.cos(yaw), np.sin(yaw)
        m[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
        m[:3, 3] = [x, y, 0.0]
        out[mid] = m
    return out


def texture(size: float, seed: int = 0) -> NDArray[np.uint8]:
    """BGR floor texture (multi-octave noise) with the markers printed on it."""
    rng = np.random.default_rng(seed)
    n = int(2 * HALF_M * TEX_PX_PER_M)
    tex = np.zeros((n, n), np.float32)
    for cells in (8, 32, 128, 512):
        small = rng.random((cells, cells)).astype(np.float32)
        tex += cv2.resize(small, (n, n), interpolation=cv2.INTER_CUBIC) / np.sqrt(cells)
    tex = (tex - tex.min()) / (tex.max() - tex.min())
    col = np.stack([tex, 1 - tex, 0.5 + 0.5 * tex], axis=-1)
    img = (col * 200 + 30).astype(np.uint8)
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    for mid, pose in marker_poses(size).items():
        side = int(size * TEX_PX_PER_M)
        mk = cv2.aruco.generateImageMarker(dictionary, mid, side)
        # marker image row r, col c → marker frame (x, y) = (c - side/2, side/2 - r) / px
        src = np.float32([[0, 0], [side, 0], [side, side], [0, side]])
        corners_m = np.array([[-1, 1], [1, 1], [1, -1], [-1, -1]]) * size / 2
        env = corners_m @ pose[:2, :2].T + pose[:2, 3]
        dst = np.float32(tex_pixels(env))
        hmat = cv2.getPerspectiveTransform(src, dst)
        border = int(0.03 * TEX_PX_PER_M)
        pad = cv2.copyMakeBorder(mk, border, border, border, border, cv2.BORDER_CONSTANT, value=255)
        hpad = hmat @ np.array([[1, 0, -border], [0, 1, -border], [0, 0, 1.0]])
        warped = cv2.warpPerspective(pad, hpad, (n, n), flags=cv2.INTER_AREA, borderValue=0)
        mask = cv2.warpPerspective(np.full_like(pad, 255), hpad, (n, n), borderValue=0) > 127
        img[mask] = warped[mask][:, None]
    return img


def tex_pixels(xy_env: NDArray[np.float64]) -> NDArray[np.float64]:
    """Env (x, y) on the floor → texture pixel (col, row); texture row 0 at y = +HALF."""
    return np.stack(
        [
            (xy_env[:, 0] + HALF_M) * TEX_PX_PER_M - 0.5,
            (HALF_M - xy_env[:, 1]) * TEX_PX_PER_M - 0.5,
        ],
        axis=1,
    )


def render(tex: NDArray[np.uint8], env_from_cam: NDArray[np.float64]) -> NDArray[np.uint8]:
    """Exact image of the floor plane via the homography image_from_texture."""
    cam_from_env = np.linalg.inv(env_from_cam)
    # texture pixel (c, r) → env (x, y, 0)
    env_from_tex = np.array(
        [
            [1 / TEX_PX_PER_M, 0, (0.5 / TEX_PX_PER_M) - HALF_M],
            [0, -1 / TEX_PX_PER_M, HALF_M - 0.5 / TEX_PX_PER_M],
            [0, 0, 1.0],
        ]
    )
    plane = cam_from_env[:3][:, [0, 1, 3]]  # (x, y, 1) on z = 0 → cam
    hmat = k_matrix() @ plane @ env_from_tex
    return np.asarray(
        cv2.warpPerspective(tex, hmat, (W, H), flags=cv2.INTER_LINEAR, borderValue=(40, 40, 40)),
        np.uint8,
    )


def ring_poses(n: int, radius: float = 0.7, height: float = 0.9) -> list[NDArray[np.float64]]:
    out = []
    for i in range(n):
        a = 2 * np.pi * i / n
        eye = np.array([radius * np.cos(a), radius * np.sin(a), height + 0.05 * np.sin(3 * a)])
        out.append(look_at(eye, np.array([0.05 * np.cos(2 * a), 0.0, 0.0])))
    return out


def write_scene(root: Path, n_views: int = 12, marker_size: float = 0.12) -> dict[str, object]:
    """Write images/, cameras.json (intrinsics + poses) and reference.json under ``root``."""
    tex = texture(marker_size)
    (root / "images").mkdir(parents=True, exist_ok=True)
    poses = {}
    for i, pose in enumerate(ring_poses(n_views)):
        name = f"view_{i:03d}.png"
        cv2.imwrite(str(root / "images" / name), render(tex, pose))
        poses[name] = pose.tolist()
    k = k_matrix()
    cameras = {
        "intrinsics": {
            "model": "PINHOLE",
            "width": W,
            "height": H,
            "params": [k[0, 0], k[1, 1], k[0, 2], k[1, 2]],
        },
        "poses": poses,
    }
    reference = {
        "markers": {
            "dictionary": "DICT_4X4_50",
            "size": marker_size,
            "poses": {str(i): p.tolist() for i, p in marker_poses(marker_size).items()},
        }
    }
    (root / "cameras.json").write_text(json.dumps(cameras))
    (root / "reference.json").write_text(json.dumps(reference))
    return {"cameras": cameras, "reference": reference}


def project(
    env_from_cam: NDArray[np.float64], points_env: NDArray[np.float64]
) -> NDArray[np.float64]:
    """(N, 2) pixels of env points in a scene camera."""
    cam_from_env = np.linalg.inv(env_from_cam)
    p = points_env @ cam_from_env[:3, :3].T + cam_from_env[:3, 3]
    uv = p[:, :2] / p[:, 2:3]
    return np.asarray(uv @ k_matrix()[:2, :2].T + k_matrix()[:2, 2], dtype=np.float64)
