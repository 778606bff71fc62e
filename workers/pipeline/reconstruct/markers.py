"""Reference markers: ArUco detection, multi-view triangulation, similarity to the env frame.

A marker's frame is OpenCV's ArUco frame (origin at the centre, x right, y up, z out of the
face); its corners, in the order ``cv2.aruco`` detects them (top-left, top-right,
bottom-right, bottom-left), sit at (−s/2, s/2, 0), (s/2, s/2, 0), (s/2, −s/2, 0),
(−s/2, −s/2, 0) for a marker of side ``s`` metres.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from app.formats import FormatError
from app.formats.reference import read_reference
from workers.pipeline.errors import InputError, ShapeError
from workers.pipeline.geometry import (
    Mat4,
    as_mat4,
    project_points,
    transform_points,
    triangulate_dlt,
    umeyama_similarity,
)
from workers.pipeline.reconstruct.cameras import CameraView
from workers.pipeline.reconstruct.common import read_image
from workers.pipeline.reconstruct.errors import MarkersNotFound


@dataclass(frozen=True)
class MarkerReference:
    """The environment's printed reference: ArUco dictionary, side in metres, env_from_marker."""

    dictionary: str
    size_m: float
    poses: dict[int, Mat4]

    def corners_env(self, marker_id: int) -> NDArray[np.float64]:
        """(4, 3) corners of one marker in the env frame, metres, in detection order."""
        return transform_points(self.poses[marker_id], marker_corners_local(self.size_m))


@dataclass(frozen=True)
class MarkerAlignment:
    """Result of fixing the env frame from markers.

    ``env_from_world`` is a 4×4 similarity (its 3×3 block is scale × rotation);
    ``residual_m`` the RMS corner distance after the fit, metres; ``per_marker_m`` each
    marker's RMS; ``used`` the marker ids kept; ``views_per_marker`` how many views saw each.
    """

    env_from_world: Mat4
    scale: float
    residual_m: float
    per_marker_m: dict[int, float]
    used: tuple[int, ...]
    views_per_marker: dict[int, int]


def marker_corners_local(size_m: float) -> NDArray[np.float64]:
    """(4, 3) corners in the marker frame in cv2.aruco detection order, metres."""
    h = size_m / 2.0
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


def parse_reference(reference: dict[str, Any] | None) -> MarkerReference | None:
    """Parse an environment ``reference`` (:mod:`app.formats.reference`); None when it has
    no markers. InputError naming the field when it is malformed."""
    if not reference or "markers" not in reference:
        return None
    try:
        sheet = read_reference(reference)
    except FormatError as exc:
        raise InputError(f"reference markers are malformed: {exc}") from exc
    assert sheet is not None  # a document with markers is a sheet or an error
    if not hasattr(cv2.aruco, sheet.dictionary):
        raise InputError(f"unknown ArUco dictionary {sheet.dictionary!r}")
    poses = {i: as_mat4(m, f"markers.poses[{i}]") for i, m in sheet.env_from_marker.items()}
    return MarkerReference(sheet.dictionary, sheet.size_m, poses)


def detect_markers(
    image_bgr: NDArray[np.uint8], dictionary: str = "DICT_4X4_50", subpixel: bool = True
) -> dict[int, NDArray[np.float64]]:
    """ArUco markers in one image: id → (4, 2) corner pixels (OpenCV convention, distorted)."""
    if image_bgr.ndim not in (2, 3):
        raise ShapeError(f"image must be (H, W) or (H, W, 3), got {image_bgr.shape}")
    gray = cv2.cvtColor(image_bgr, cv2.COLOR_BGR2GRAY) if image_bgr.ndim == 3 else image_bgr
    params = cv2.aruco.DetectorParameters()
    if subpixel:
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        params.cornerRefinementWinSize = 4
        params.cornerRefinementMinAccuracy = 0.01
    detector = cv2.aruco.ArucoDetector(
        cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)), params
    )
    corners, ids, _ = detector.detectMarkers(gray)
    out: dict[int, NDArray[np.float64]] = {}
    if ids is None:
        return out
    for c, i in zip(corners, ids.reshape(-1), strict=True):
        out[int(i)] = np.asarray(c, dtype=np.float64).reshape(4, 2)
    return out


def _undistort(view: CameraView, pixels: NDArray[np.float64]) -> NDArray[np.float64]:
    dist = view.intrinsics.dist_coeffs
    if not np.any(dist):
        return pixels
    k = view.intrinsics.k_matrix
    out = cv2.undistortPoints(pixels.reshape(-1, 1, 2), k, dist, P=k)
    return np.asarray(out, dtype=np.float64).reshape(-1, 2)


def triangulate_corners(
    views: list[CameraView] | tuple[CameraView, ...],
    detections: dict[str, dict[int, NDArray[np.float64]]],
    min_views: int = 2,
    max_reprojection_px: float = 3.0,
) -> tuple[dict[int, NDArray[np.float64]], dict[int, int]]:
    """Triangulate each marker's 4 corners by multi-view DLT in the views' frame.

    ``views[i].env_from_cam`` is frame_from_cam; ``detections`` maps image name → id →
    (4, 2) pixels. Views whose reprojection error exceeds ``max_reprojection_px`` are dropped
    and the corners re-triangulated. Returns (id → (4, 3) corners, id → number of views).
    """
    by_name = {v.name: v for v in views}
    seen: dict[int, list[tuple[CameraView, NDArray[np.float64]]]] = {}
    for name, dets in detections.items():
        if name not in by_name:
            continue
        for mid, px in dets.items():
            seen.setdefault(mid, []).append((by_name[name], _undistort(by_name[name], px)))
    corners: dict[int, NDArray[np.float64]] = {}
    counts: dict[int, int] = {}
    for mid, obs in seen.items():
        for _ in range(2):
            if len(obs) < min_views:
                break
            proj = np.stack([v.intrinsics.k_matrix @ v.cam_from_env[:3] for v, _ in obs])
            pts = np.stack(
                [triangulate_dlt(proj, np.stack([px[c] for _, px in obs])) for c in range(4)]
            )
            errs = np.array(
                [
                    np.sqrt(
                        np.nanmean(
                            np.sum(
                                (project_points(v.intrinsics.k_matrix, v.cam_from_env, pts)[0] - px)
                                ** 2,
                                axis=1,
                            )
                        )
                    )
                    for v, px in obs
                ]
            )
            keep = np.nan_to_num(errs, nan=np.inf) <= max_reprojection_px
            corners[mid], counts[mid] = pts, len(obs)
            if keep.all():
                break
            obs = [o for o, k in zip(obs, keep, strict=True) if k]
            if len(obs) < min_views:
                corners.pop(mid)
                counts.pop(mid)
    return corners, counts


def align_to_markers(
    corners_world: dict[int, NDArray[np.float64]],
    views_per_marker: dict[int, int],
    reference: MarkerReference,
) -> MarkerAlignment:
    """Umeyama similarity env_from_world from triangulated corners to the reference corners.

    Markers whose own RMS exceeds 3× the median (and 5 mm) after a first fit are dropped and
    the fit repeated. Raises MarkersNotFound when no reference marker was triangulated.
    """
    ids = sorted(i for i in corners_world if i in reference.poses)
    if not ids:
        raise MarkersNotFound(
            "none of the reference markers "
            f"{sorted(reference.poses)} was seen in two or more registered images; make sure "
            "the printed markers are visible and sharp in several photos"
        )
    used = ids
    for _ in range(2):
        src = np.concatenate([corners_world[i] for i in used])
        dst = np.concatenate([reference.corners_env(i) for i in used])
        env_from_world, scale = umeyama_similarity(src, dst)
        per = {
            i: float(
                np.sqrt(
                    np.mean(
                        np.sum(
                            (
                                transform_points(env_from_world, corners_world[i])
                                - reference.corners_env(i)
                            )
                            ** 2,
                            axis=1,
                        )
                    )
                )
            )
            for i in ids
        }
        med = float(np.median([per[i] for i in used]))
        keep = [i for i in used if per[i] <= max(3.0 * med, 0.005)]
        if keep == used or len(keep) == 0:
            break
        used = keep
    src = np.concatenate([corners_world[i] for i in used])
    dst = np.concatenate([reference.corners_env(i) for i in used])
    env_from_world, scale = umeyama_similarity(src, dst)
    resid = transform_points(env_from_world, src) - dst
    rms = float(np.sqrt(np.mean(np.sum(resid**2, axis=1))))
    return MarkerAlignment(
        env_from_world, scale, rms, per, tuple(used), {i: views_per_marker[i] for i in ids}
    )


def detect_in_images(
    images_dir: Path, names: list[str], dictionary: str, subpixel: bool
) -> dict[str, dict[int, NDArray[np.float64]]]:
    """Detect markers in every named image: name → id → (4, 2) pixels."""
    return {
        n: detect_markers(read_image(Path(images_dir) / n), dictionary, subpixel) for n in names
    }


def check_markers_in_env(
    views: tuple[CameraView, ...],
    detections: dict[str, dict[int, NDArray[np.float64]]],
    reference: MarkerReference,
    min_views: int = 2,
) -> float | None:
    """RMS distance (m) of markers triangulated with env-frame cameras to their reference
    corners, with no fit (a check of given poses); None when no marker was triangulated."""
    corners, _ = triangulate_corners(views, detections, min_views)
    ids = [i for i in corners if i in reference.poses]
    if not ids:
        return None
    d = np.concatenate([corners[i] - reference.corners_env(i) for i in ids])
    return float(np.sqrt(np.mean(np.sum(d**2, axis=1))))
