"""The reconstruct stage: photos → every camera's intrinsics and env_from_cam, and a dense
coloured cloud in metres in the environment frame.

Outputs under ``work_dir``: ``cloud.ply`` (binary, coloured, env frame), ``cameras.json``
(per-image intrinsics and env_from_cam poses: the cameras.json the next stages read) and
``quality.json``; working artefacts in ``work_dir/sfm`` (resumable).
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
from workers.pipeline.reconstruct.cameras import CamerasSpec, CameraView, write_cameras
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


@dataclass(frozen=True)
class _Run:
    """The checked inputs of one run: the photo names (sorted), the marker reference (None:
    none given), and whether ``cameras`` gives every image a pose (``known``) or how many
    it gives (``n_posed``)."""

    images_dir: Path
    work_dir: Path
    names: list[str]
    options: ReconstructOptions
    cameras: CamerasSpec | None
    marker_ref: markers.MarkerReference | None
    known: bool
    n_posed: int


@dataclass(frozen=True)
class _Frame:
    """The cameras in the env frame and the sparse points the dense step starts from:
    ``points_env`` (N, 3) metres, ``visibility`` (N, V) bool; ``sparse`` the env-frame SfM
    model (None with known poses), ``dense_views`` the views already loaded for MVS (None:
    not yet), ``quality`` this step's entries of quality.json."""

    views: tuple[CameraView, ...]
    points_env: NDArray[np.float64]
    visibility: NDArray[np.bool_]
    sparse: SparseModel | None
    dense_views: list[mvs.DenseView] | None
    quality: dict[str, Any]


@dataclass(frozen=True)
class _DenseCloud:
    """The fused cloud, (M, 3) env metres and (M, 3) uint8 RGB; ``measured_env`` (K, 3) the
    points the alignment to the previous snapshot follows; ``quality`` this step's entries."""

    points_env: NDArray[np.float64]
    colors_rgb: NDArray[np.uint8]
    measured_env: NDArray[np.float64]
    quality: dict[str, Any]


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
    run = _checked_inputs(Path(images_dir), Path(work_dir), options, cameras, reference)
    quality: dict[str, Any] = {
        "preset": options.preset,
        "far_range": options.far_range,
        "images_total": len(run.names),
        "mode": "known_poses" if run.known else "sfm",
        "marker_residual_m": None,
        "marker_scale": None,
        "markers_used": [],
    }
    frame = _known_pose_frame(run, clock) if run.known else _sfm_frame(run, clock)
    quality.update(frame.quality)
    quality["images_registered"] = len(frame.views)
    ref_pts = _reference_points(reference_cloud)
    dense = _dense_cloud(run, frame, ref_pts, clock)
    quality.update(dense.quality)
    cloud_pts, env_views = dense.points_env, frame.views
    alignment: AlignmentResult | None = None
    if ref_pts is not None:
        clock("alignment", 0.0)
        alignment = refine_alignment(dense.measured_env, ref_pts, options)
        if alignment.applied:
            m = alignment.env_from_new
            cloud_pts = cloud_pts @ m[:3, :3].T + m[:3, 3]
            env_views = tuple(v.with_pose(m @ v.env_from_cam) for v in env_views)
    quality["alignment_residual_m"] = alignment.residual_m if alignment else None
    quality["alignment_correction"] = alignment.to_json() if alignment else None
    quality["points"] = len(cloud_pts)

    clock("write", 0.0)
    cloud_path = run.work_dir / "cloud.ply"
    cameras_path = run.work_dir / "cameras.json"
    quality_path = run.work_dir / "quality.json"
    fusion.write_ply(cloud_path, cloud_pts, dense.colors_rgb)
    write_cameras(cameras_path, env_views)
    clock.stop()
    quality["timings_s"] = dict(clock.timings, total=round(time.perf_counter() - t0, 3))
    quality_path.write_text(json.dumps(quality, indent=1, default=_json_default))
    clock.progress("done", 1.0)
    return ReconstructionResult(cloud_path, cameras_path, quality_path, env_views, quality)


def _checked_inputs(
    images_dir: Path,
    work_dir: Path,
    options: ReconstructOptions,
    cameras: CamerasSpec | None,
    reference: dict[str, Any] | None,
) -> _Run:
    """Create ``work_dir`` and check that the photos can be reconstructed and placed in the
    env frame; raises TooFewImages, InputError, NoReferenceFrame."""
    work_dir.mkdir(parents=True, exist_ok=True)
    names = list_images(images_dir)
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
    return _Run(images_dir, work_dir, names, options, cameras, marker_ref, known, n_posed)


def _known_pose_frame(run: _Run, clock: _Clock) -> _Frame:
    """The given poses as the env frame (markers only checked against them) and sparse
    points triangulated from ORB matches between the loaded MVS views."""
    assert run.cameras is not None
    views = []
    for n in run.names:
        intr = run.cameras.intrinsics_for(n)
        assert intr is not None
        views.append(CameraView(n, intr, run.cameras.poses[n]))
    env_views = tuple(views)
    quality: dict[str, Any] = {"frame_source": "camera_poses", "mean_reprojection_error_px": None}
    options = run.options
    if run.marker_ref is not None:
        clock("markers", 0.0)
        dets = markers.detect_in_images(
            run.images_dir, run.names, run.marker_ref.dictionary, options.marker_subpixel
        )
        quality["marker_residual_m"] = markers.check_markers_in_env(
            env_views, dets, run.marker_ref, options.min_marker_views
        )
    clock("sparse", 0.0)
    dense_views = mvs.load_dense_views(
        run.images_dir, env_views, options.mvs_scale, options.mvs_max_image_size
    )
    pts, vis = known_poses.triangulate_known(dense_views, options)
    quality["sparse_points"] = len(pts)
    return _Frame(env_views, pts, vis, None, dense_views, quality)


def _sfm_frame(run: _Run, clock: _Clock) -> _Frame:
    """Structure from motion, placed in the env frame by the markers, or by the given camera
    poses where the markers are not found (or not given)."""
    sfm_sparse = run_sfm(run.images_dir, run.work_dir, run.names, run.options, run.cameras, clock)
    quality: dict[str, Any] = {"mean_reprojection_error_px": sfm_sparse.mean_reprojection_error_px}
    fit = _marker_fit(run, sfm_sparse, clock)
    if fit is not None:
        env_from_world = fit.env_from_world
        quality.update(
            frame_source="markers",
            marker_residual_m=fit.residual_m,
            marker_scale=fit.scale,
            markers_used=list(fit.used),
            marker_views=fit.views_per_marker,
        )
    else:
        assert run.cameras is not None
        env_from_world, rms = _frame_from_poses(sfm_sparse, run.cameras)
        quality.update(frame_source="camera_poses", camera_pose_residual_m=rms)
    sparse = sfm_sparse.transformed(env_from_world)
    quality["sparse_points"] = len(sparse.points)
    return _Frame(sparse.views, sparse.points, sparse.visibility, sparse, None, quality)


def _marker_fit(
    run: _Run, sfm_sparse: SparseModel, clock: _Clock
) -> markers.MarkerAlignment | None:
    """env_from_world from the markers seen by the registered views; None without a marker
    reference, or when the markers are not found but ≥ 3 images have given poses (else
    MarkersNotFound)."""
    if run.marker_ref is None:
        return None
    clock("markers", 0.0)
    registered = [v.name for v in sfm_sparse.views]
    dets = markers.detect_in_images(
        run.images_dir, registered, run.marker_ref.dictionary, run.options.marker_subpixel
    )
    corners, counts = markers.triangulate_corners(
        sfm_sparse.views, dets, run.options.min_marker_views
    )
    try:
        return markers.align_to_markers(corners, counts, run.marker_ref)
    except MarkersNotFound:
        if run.cameras is None or run.n_posed < 3:
            raise
        return None


def _reference_points(reference_cloud: Path | None) -> NDArray[np.float64] | None:
    """The previous snapshot's (M, 3) env points, None when not given; InputError if empty."""
    if reference_cloud is None:
        return None
    ref_pts, _ = fusion.read_ply(Path(reference_cloud))
    if len(ref_pts) == 0:
        raise InputError(f"reference cloud {reference_cloud} is empty or unreadable")
    return ref_pts


def _dense_cloud(
    run: _Run, frame: _Frame, ref_pts: NDArray[np.float64] | None, clock: _Clock
) -> _DenseCloud:
    """The dense cloud: pycolmap's CUDA PatchMatch where asked for and possible (SfM mode on
    a CUDA build), else the CPU stereo (:func:`_cpu_dense`)."""
    if (
        run.options.cuda_dense and pycolmap.has_cuda and frame.sparse is not None
    ):  # pragma: no cover
        clock("dense", 0.0)
        cloud_pts, cloud_cols = _cuda_dense(run.images_dir, run.work_dir, frame.sparse)
        return _DenseCloud(cloud_pts, cloud_cols, cloud_pts, {"dense_method": "colmap_patch_match"})
    return _cpu_dense(run, frame, ref_pts, clock)


def _cpu_dense(
    run: _Run, frame: _Frame, ref_pts: NDArray[np.float64] | None, clock: _Clock
) -> _DenseCloud:
    """SGBM depth maps, the planar prior (with ``planar_prior``), the consistency check and
    voxel fusion. The alignment follows only measured points nearer than
    ``far_min_depth_m`` when plane depths joined the cloud."""
    options = run.options
    quality: dict[str, Any] = {}
    clock("load", 0.0)
    dense_views = frame.dense_views
    if dense_views is None:
        dense_views = mvs.load_dense_views(
            run.images_dir, frame.views, options.mvs_scale, options.mvs_max_image_size
        )
    clock("neighbours", 0.0)
    pts, vis = frame.points_env, frame.visibility
    nbrs = mvs.select_neighbours(dense_views, pts, vis, options)
    if not any(nbrs.stereo):
        raise DenseReconstructionFailed(
            "no well-conditioned stereo pair (enough shared points, baseline and viewing "
            "angle); take photos from more positions around the scene"
        )
    maps = mvs.compute_depth_maps(dense_views, nbrs, pts, vis, options, clock)
    depths = maps.fused
    verified = None
    if options.planar_prior:
        planes_ref = ref_pts if options.planar_reference_planes else None
        fill = _planar_prior(dense_views, maps, nbrs, planes_ref, options, clock)
        quality["planar"] = fill.stats
        depths, verified = fill.depths, fill.verified()
    raw = mvs.consistent_points_split(dense_views, depths, nbrs, options, clock, verified)
    quality["points_before_fusion"] = len(raw.points_env)
    clock("fusion", 0.0)
    cloud_pts, cloud_cols = fusion.fuse_points(raw.points_env, raw.colors_rgb, options)
    measured_pts = cloud_pts
    if raw.verified.any():
        # what the alignment to the previous snapshot follows: plane depths are a prior,
        # and two captures' planes (or one's planes and the other's far SGBM points,
        # biased by 2-4 mm) lie 1-2 mm apart, which pulls the ICP by as much
        measured_pts = raw.points_env[~raw.verified & (raw.depth_m < options.far_min_depth_m)]
    quality["dense_method"] = "cpu_sgbm"
    return _DenseCloud(cloud_pts, cloud_cols, measured_pts, quality)


def _planar_prior(
    views: list[mvs.DenseView],
    maps: mvs.DepthMaps,
    nbrs: mvs.Neighbours,
    reference_pts: NDArray[np.float64] | None,
    options: ReconstructOptions,
    clock: _Clock,
) -> planar.PlaneFill:
    """The fused depth maps with verified plane depths laid in (planar.py), planes detected
    in a first consistency pass over every ``planar_seed_stride``-th pixel of the plane-seed
    maps (far depths checked against the views that confirm most of them too:
    :func:`mvs.with_far_confirming_neighbours`), then in the environment's (M, 3)
    ``reference_pts`` cloud when given; its ``stats`` are quality.json's ``planar``
    (planes, pixels filled, far depths replaced)."""
    clock("planar", 0.0)
    seed_nbrs = mvs.with_far_confirming_neighbours(views, maps.plane_seed, nbrs, options)
    seed_pts, _ = mvs.consistent_points(
        views,
        maps.plane_seed,
        seed_nbrs,
        dataclasses.replace(options, point_stride=options.planar_seed_stride),
    )
    found = planar.detect_planes(seed_pts, options, reference_pts)
    return planar.fill_depths(views, maps.fused, found, options, clock)


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
