"""The reconstruct stage: photos → every camera's intrinsics and env_from_cam, and a dense
coloured cloud in metres in the environment frame.

Outputs under ``work_dir``: ``cloud.ply`` (binary, coloured, env frame), ``cameras.json``
(per image K, dist, width, height, env_from_cam) and ``quality.json``; working artefacts
in ``work_dir/sfm`` (resumable).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap
from numpy.typing import NDArray

from workers.pipeline.errors import InputError
from workers.pipeline.geometry import Mat4, umeyama_similarity
from workers.pipeline.reconstruct import fusion, known_poses, markers, mvs, planar
from workers.pipeline.reconstruct.align import AlignmentResult, refine_alignment
from workers.pipeline.reconstruct.cameras import CamerasSpec, CameraView
from workers.pipeline.reconstruct.common import Progress, list_images, no_progress
from workers.pipeline.reconstruct.errors import (
    DenseReconstructionFailed,
    MarkersNotFound,
    NoReferenceFrame,
    TooFewImages,
)
from workers.pipeline.reconstruct.options import ReconstructOptions
from workers.pipeline.reconstruct.sfm import SparseModel, run_sfm

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ReconstructionResult:
    """What the stage produced. ``views`` carry env_from_cam (4×4 rigid, metres, OpenCV axes).

    ``quality`` holds images_total, images_registered, points, mean_reprojection_error_px,
    marker_residual_m, alignment_residual_m, alignment_correction, timings_s and more (see
    ``quality.json``).
    """

    cloud_path: Path
    cameras_path: Path
    quality_path: Path
    views: tuple[CameraView, ...]
    quality: dict[str, Any]


class _Clock:
    """Wall time per named stage, fed by the stage's own progress calls."""

    def __init__(self, progress: Progress) -> None:
        self.progress = progress
        self.timings: dict[str, float] = {}
        self._stage: str | None = None
        self._start = time.perf_counter()

    def __call__(self, stage: str, fraction: float) -> None:
        if stage != self._stage:
            self.stop()
            self._stage, self._start = stage, time.perf_counter()
        self.progress(stage, fraction)

    def stop(self) -> None:
        if self._stage is not None:
            elapsed = time.perf_counter() - self._start
            self.timings[self._stage] = round(self.timings.get(self._stage, 0.0) + elapsed, 3)
            self._stage = None


def _frame_from_poses(sparse: SparseModel, cameras: CamerasSpec) -> tuple[Mat4, float]:
    """env_from_world by Umeyama on camera centres with given poses; (similarity, RMS m)."""
    pairs = [
        (v.centre, cameras.poses[v.name][:3, 3]) for v in sparse.views if v.name in cameras.poses
    ]
    src = np.stack([a for a, _ in pairs])
    dst = np.stack([b for _, b in pairs])
    env_from_world, _ = umeyama_similarity(src, dst)
    moved = src @ env_from_world[:3, :3].T + env_from_world[:3, 3]
    return env_from_world, float(np.sqrt(np.mean(np.sum((moved - dst) ** 2, axis=1))))


def reconstruct(
    images_dir: Path,
    work_dir: Path,
    options: ReconstructOptions,
    cameras: CamerasSpec | None = None,
    reference: dict[str, Any] | None = None,
    reference_cloud: Path | None = None,
    progress: Progress | None = None,
) -> ReconstructionResult:
    """Reconstruct one snapshot from the photos in ``images_dir``.

    ``cameras`` (cameras.json) may give intrinsics and env_from_cam poses; with poses for
    every image SfM is skipped. ``reference`` is the environment's {"markers": ...}
    reference; ``reference_cloud`` the previous snapshot's cloud (env frame) to refine the
    alignment against. Writes only under ``work_dir``.

    Raises TooFewImages, NoReferenceFrame, ImagesDoNotOverlap, TooFewImagesRegistered,
    MarkersNotFound, DenseReconstructionFailed (all ReconstructionError), InputError.
    """
    t0 = time.perf_counter()
    clock = _Clock(progress or no_progress)
    work_dir = Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    names = list_images(Path(images_dir))
    if len(names) < max(options.min_images, 2):
        raise TooFewImages(
            f"{len(names)} image(s) in the snapshot; a reconstruction needs at least "
            f"{max(options.min_images, 2)} overlapping photos"
        )
    marker_ref = markers.parse_reference(reference)
    known = cameras is not None and cameras.has_all_poses(names)
    if known and cameras is not None and not cameras.has_all_intrinsics(names):
        raise InputError("cameras.json gives every pose but not every image's intrinsics")
    n_posed = sum(1 for n in names if cameras is not None and n in cameras.poses)
    if not known and marker_ref is None and n_posed < 3:
        raise NoReferenceFrame(
            "NoReferenceFrame: give reference markers in the environment (reference.markers) "
            "or camera poses (env_from_cam) in cameras.json"
        )
    quality: dict[str, Any] = {
        "preset": options.preset,
        "far_range": options.far_range,
        "images_total": len(names),
        "mode": "known_poses" if known else "sfm",
        "marker_residual_m": None,
        "marker_scale": None,
        "markers_used": [],
    }

    sparse: SparseModel | None = None
    dense_views: list[mvs.DenseView] | None = None
    if known and cameras is not None:
        views = []
        for n in names:
            intr = cameras.intrinsics_for(n)
            assert intr is not None
            views.append(CameraView(n, intr, cameras.poses[n]))
        env_views = tuple(views)
        quality["frame_source"] = "camera_poses"
        quality["mean_reprojection_error_px"] = None
        if marker_ref is not None:
            clock("markers", 0.0)
            dets = markers.detect_in_images(
                Path(images_dir), names, marker_ref.dictionary, options.marker_subpixel
            )
            quality["marker_residual_m"] = markers.check_markers_in_env(
                env_views, dets, marker_ref, options.min_marker_views
            )
        clock("sparse", 0.0)
        dense_views = mvs.load_dense_views(Path(images_dir), env_views, options.mvs_scale)
        pts, vis = known_poses.triangulate_known(dense_views, options)
        quality["sparse_points"] = len(pts)
    else:
        sfm_sparse = run_sfm(Path(images_dir), work_dir, names, options, cameras, clock)
        quality["mean_reprojection_error_px"] = sfm_sparse.mean_reprojection_error_px
        registered = [v.name for v in sfm_sparse.views]
        if marker_ref is not None:
            clock("markers", 0.0)
            dets = markers.detect_in_images(
                Path(images_dir), registered, marker_ref.dictionary, options.marker_subpixel
            )
            corners, counts = markers.triangulate_corners(
                sfm_sparse.views, dets, options.min_marker_views
            )
            try:
                fit = markers.align_to_markers(corners, counts, marker_ref)
            except MarkersNotFound:
                if cameras is None or n_posed < 3:
                    raise
                fit = None
            if fit is not None:
                env_from_world = fit.env_from_world
                quality.update(
                    frame_source="markers",
                    marker_residual_m=fit.residual_m,
                    marker_scale=fit.scale,
                    markers_used=list(fit.used),
                    marker_views=fit.views_per_marker,
                )
        if quality.get("frame_source") is None:
            assert cameras is not None
            env_from_world, rms = _frame_from_poses(sfm_sparse, cameras)
            quality.update(frame_source="camera_poses", camera_pose_residual_m=rms)
        sparse = sfm_sparse.transformed(env_from_world)
        env_views = sparse.views
        pts, vis = sparse.points, sparse.visibility
        quality["sparse_points"] = len(pts)
    quality["images_registered"] = len(env_views)
    ref_pts: NDArray[np.float64] | None = None
    if reference_cloud is not None:
        ref_pts, _ = fusion.read_ply(Path(reference_cloud))
        if len(ref_pts) == 0:
            raise InputError(f"reference cloud {reference_cloud} is empty or unreadable")

    if options.cuda_dense and pycolmap.has_cuda and sparse is not None:  # pragma: no cover
        clock("dense", 0.0)
        cloud_pts, cloud_cols = _cuda_dense(Path(images_dir), work_dir, sparse)
        measured_pts = cloud_pts
        quality["dense_method"] = "colmap_patch_match"
    else:
        clock("load", 0.0)
        if dense_views is None:
            dense_views = mvs.load_dense_views(Path(images_dir), env_views, options.mvs_scale)
        clock("neighbours", 0.0)
        nbrs = mvs.select_neighbours(dense_views, pts, vis, options)
        if not any(nbrs.stereo):
            raise DenseReconstructionFailed(
                "no well-conditioned stereo pair (enough shared points, baseline and viewing "
                "angle); take photos from more positions around the scene"
            )
        maps = mvs.compute_depth_maps(dense_views, nbrs, pts, vis, options, clock)
        depths = maps.fused
        fill = None
        if options.planar_prior:
            planes_ref = ref_pts if options.planar_reference_planes else None
            fill = _planar_prior(dense_views, maps, nbrs, planes_ref, options, clock, quality)
            depths = fill.depths
        raw_pts, raw_cols, from_plane, raw_depth = mvs.consistent_points_split(
            dense_views,
            depths,
            nbrs,
            options,
            clock,
            fill.from_plane if fill else None,
            fill.checked_by if fill else None,
            fill.fallback if fill else None,
        )
        quality["points_before_fusion"] = len(raw_pts)
        clock("fusion", 0.0)
        cloud_pts, cloud_cols = fusion.fuse_points(raw_pts, raw_cols, options)
        measured_pts = cloud_pts
        if from_plane.any():
            # what the alignment to the previous snapshot follows: plane depths are a prior,
            # and two captures' planes (or one's planes and the other's far SGBM points,
            # biased by 2-4 mm) lie 1-2 mm apart, which pulls the ICP by as much
            measured_pts = raw_pts[~from_plane & (raw_depth < options.far_min_depth_m)]
        quality["dense_method"] = "cpu_sgbm"

    alignment: AlignmentResult | None = None
    if ref_pts is not None:
        clock("alignment", 0.0)
        alignment = refine_alignment(measured_pts, ref_pts, options)
        if alignment.applied:
            m = alignment.env_from_new
            cloud_pts = cloud_pts @ m[:3, :3].T + m[:3, 3]
            env_views = tuple(v.with_pose(m @ v.env_from_cam) for v in env_views)
    quality["alignment_residual_m"] = alignment.residual_m if alignment else None
    quality["alignment_correction"] = alignment.to_json() if alignment else None
    quality["points"] = len(cloud_pts)

    clock("write", 0.0)
    cloud_path = work_dir / "cloud.ply"
    cameras_path = work_dir / "cameras.json"
    quality_path = work_dir / "quality.json"
    fusion.write_ply(cloud_path, cloud_pts, cloud_cols)
    cameras_path.write_text(
        json.dumps({"images": {v.name: v.to_json() for v in env_views}}, indent=1)
    )
    clock.stop()
    quality["timings_s"] = dict(clock.timings, total=round(time.perf_counter() - t0, 3))
    quality_path.write_text(json.dumps(quality, indent=1, default=_json_default))
    clock.progress("done", 1.0)
    return ReconstructionResult(cloud_path, cameras_path, quality_path, env_views, quality)


def _planar_prior(
    views: list[mvs.DenseView],
    maps: mvs.DepthMaps,
    nbrs: mvs.Neighbours,
    reference_pts: NDArray[np.float64] | None,
    options: ReconstructOptions,
    clock: _Clock,
    quality: dict[str, Any],
) -> planar.PlaneFill:
    """The fused depth maps with verified plane depths laid in (planar.py), planes detected
    in a first consistency pass over every ``planar_seed_stride``-th pixel of the plane-seed
    maps (far depths checked against the views that confirm most of them too:
    :func:`mvs.with_far_confirming_neighbours`), then in the environment's (M, 3)
    ``reference_pts`` cloud when given; records ``quality["planar"]`` (planes,
    pixels filled, far depths replaced or snapped)."""
    clock("planar", 0.0)
    seed_nbrs = mvs.with_far_confirming_neighbours(views, maps.plane_seed, nbrs, options)
    seed_pts, _ = mvs.consistent_points(
        views,
        maps.plane_seed,
        seed_nbrs,
        dataclasses.replace(options, point_stride=options.planar_seed_stride),
    )
    found = planar.detect_planes(seed_pts, options, reference_pts)
    fill = planar.fill_depths(views, maps.fused, found, options, clock)
    quality["planar"] = fill.stats
    return fill


def _json_default(obj: object) -> object:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"not JSON serialisable: {type(obj)}")


def _cuda_dense(  # pragma: no cover - needs a CUDA build of pycolmap
    images_dir: Path, work_dir: Path, sparse: SparseModel
) -> tuple[NDArray[np.float64], NDArray[np.uint8]]:
    """Write the env-frame sparse model as a COLMAP model and run PatchMatch + fusion."""
    rec = pycolmap.Reconstruction(str(work_dir / "sfm" / "model"))
    env_rec_dir = work_dir / "sfm" / "model_env"
    env_rec_dir.mkdir(parents=True, exist_ok=True)
    # recompute the similarity from the camera centres (exact up to float error)
    src = np.stack([rec.find_image_with_name(v.name).projection_center() for v in sparse.views])
    dst = np.stack([v.centre for v in sparse.views])
    env_from_world, scale = umeyama_similarity(src, dst)
    rot = env_from_world[:3, :3] / scale
    rec.transform(pycolmap.Sim3d(scale, pycolmap.Rotation3d(rot), env_from_world[:3, 3]))
    rec.write_binary(str(env_rec_dir))
    return fusion.colmap_dense(env_rec_dir, images_dir, work_dir)
