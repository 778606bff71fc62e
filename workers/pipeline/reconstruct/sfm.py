"""Structure from motion with pycolmap (CPU): SIFT, matching, incremental mapping, BA.

Artefacts under ``<work_dir>/sfm``: ``database.db`` (+ ``features.done``, ``matches.done``
markers) and ``model/`` (the registered reconstruction); each step is skipped when its
artefact exists, so a rerun resumes.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap
from numpy.typing import NDArray

from workers.pipeline.geometry import Mat4, invert_rigid
from workers.pipeline.reconstruct import pairs
from workers.pipeline.reconstruct.cameras import (
    CamerasSpec,
    CameraView,
    Intrinsics,
    intrinsics_from_colmap,
)
from workers.pipeline.reconstruct.common import Progress, no_progress
from workers.pipeline.reconstruct.errors import ImagesDoNotOverlap, TooFewImagesRegistered
from workers.pipeline.reconstruct.options import ReconstructOptions

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SparseModel:
    """Registered cameras and sparse points, in one frame (SfM's own, or the env frame).

    ``views[i].env_from_cam`` holds ``frame_from_cam``; ``points`` (N, 3) in that frame;
    ``colors`` (N, 3) uint8 RGB; ``visibility`` (N, V) bool, True where view i sees point n.
    """

    views: tuple[CameraView, ...]
    points: NDArray[np.float64]
    colors: NDArray[np.uint8]
    visibility: NDArray[np.bool_]
    mean_reprojection_error_px: float

    def transformed(self, new_from_old: Mat4) -> SparseModel:
        """This model mapped by a 4×4 similarity (s·R | t); camera poses stay rigid."""
        sr = new_from_old[:3, :3]
        scale = float(np.cbrt(np.linalg.det(sr)))
        rot = sr / scale
        views = []
        for v in self.views:
            m = np.eye(4)
            m[:3, :3] = rot @ v.env_from_cam[:3, :3]
            m[:3, 3] = sr @ v.env_from_cam[:3, 3] + new_from_old[:3, 3]
            views.append(v.with_pose(m))
        pts = self.points @ sr.T + new_from_old[:3, 3]
        return SparseModel(
            tuple(views), pts, self.colors, self.visibility, self.mean_reprojection_error_px
        )


def _extract(
    database: Path,
    images_dir: Path,
    image_names: list[str],
    cameras: CamerasSpec | None,
    options: ReconstructOptions,
) -> None:
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = options.max_image_size
    extraction.num_threads = options.num_threads
    extraction.sift.max_num_features = options.max_num_features
    groups: dict[Intrinsics | None, list[str]] = {}
    for name in image_names:
        groups.setdefault(cameras.intrinsics_for(name) if cameras else None, []).append(name)
    for intr, names in groups.items():
        reader = pycolmap.ImageReaderOptions()
        if intr is not None:
            reader.camera_model = intr.model
            reader.camera_params = ",".join(f"{v:.10g}" for v in intr.colmap_params())
        pycolmap.extract_features(
            database,
            images_dir,
            image_names=names,
            camera_mode=pycolmap.CameraMode.SINGLE,
            reader_options=reader,
            extraction_options=extraction,
            device=pycolmap.Device.cpu,
        )


def _match(
    database: Path, sfm_dir: Path, image_names: list[str], options: ReconstructOptions
) -> None:
    """Exhaustive matching up to ``exhaustive_max_images`` photos, else the pairs of
    :func:`pairs.matching_pairs` (sequential + retrieval), written to ``sfm/pairs.txt``."""
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = options.num_threads
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = options.seed
    if len(image_names) <= options.exhaustive_max_images:
        pycolmap.match_exhaustive(
            database,
            matching_options=matching,
            verification_options=verification,
            device=pycolmap.Device.cpu,
        )
        return
    db = pycolmap.Database.open(database)
    try:
        ids = {im.name: im.image_id for im in db.read_all_images()}
        descriptors = [np.asarray(db.read_descriptors(ids[n]).data) for n in image_names]
    finally:
        db.close()
    chosen = pairs.matching_pairs(
        descriptors, options.sequential_overlap, options.loop_neighbours, options.seed
    )
    pair_file = sfm_dir / "pairs.txt"
    pair_file.write_text("".join(f"{image_names[i]} {image_names[j]}\n" for i, j in chosen))
    pairing = pycolmap.ImportedPairingOptions()
    pairing.match_list_path = pair_file
    pycolmap.match_image_pairs(
        database,
        matching_options=matching,
        pairing_options=pairing,
        verification_options=verification,
        device=pycolmap.Device.cpu,
    )


def _map(
    database: Path,
    images_dir: Path,
    model_dir: Path,
    n_images: int,
    fixed_intrinsics: bool,
    options: ReconstructOptions,
    progress: Progress,
) -> pycolmap.Reconstruction:
    if n_images > options.incremental_max_images:
        return _map_global(database, images_dir, model_dir, fixed_intrinsics, options, progress)
    pipeline = pycolmap.IncrementalPipelineOptions()
    pipeline.random_seed = options.seed
    pipeline.num_threads = options.num_threads
    pipeline.min_model_size = 3
    pipeline.ba_refine_focal_length = not fixed_intrinsics
    pipeline.ba_refine_extra_params = not fixed_intrinsics
    pipeline.ba_refine_principal_point = False
    count = [0]

    def on_image() -> None:
        count[0] += 1
        progress("mapping", min(1.0, count[0] / max(n_images, 1)))

    (model_dir.parent / "mapper_out").mkdir(parents=True, exist_ok=True)
    models = pycolmap.incremental_mapping(
        database,
        images_dir,
        model_dir.parent / "mapper_out",
        pipeline,
        next_image_callback=on_image,
    )
    return _keep_largest(models, model_dir)


def _map_global(
    database: Path,
    images_dir: Path,
    model_dir: Path,
    fixed_intrinsics: bool,
    options: ReconstructOptions,
    progress: Progress,
) -> pycolmap.Reconstruction:
    """Global SfM (GLOMAP: rotation averaging, global positioning, one bundle adjustment):
    its time grows far slower with the number of images than incremental mapping's."""
    pipeline = pycolmap.GlobalPipelineOptions()
    pipeline.random_seed = options.seed
    pipeline.num_threads = options.num_threads
    pipeline.min_model_size = 3
    ba = pipeline.mapper.bundle_adjustment
    ba.refine_focal_length = not fixed_intrinsics
    ba.refine_extra_params = not fixed_intrinsics
    ba.refine_principal_point = False
    progress("mapping", 0.0)
    out = model_dir.parent / "mapper_out"
    out.mkdir(parents=True, exist_ok=True)
    models = pycolmap.global_mapping(database, images_dir, out, pipeline)
    progress("mapping", 1.0)
    return _keep_largest(models, model_dir)


def _keep_largest(
    models: dict[int, pycolmap.Reconstruction], model_dir: Path
) -> pycolmap.Reconstruction:
    """The model with the most registered images, written to ``model_dir``; raises
    ImagesDoNotOverlap when SfM made none."""
    if not models:
        raise ImagesDoNotOverlap(
            "structure from motion found no overlapping image pair to start from; take photos "
            "with more overlap (each part of the scene in ≥ 3 photos) and more texture"
        )
    best = max(models.values(), key=lambda r: r.num_reg_images())
    model_dir.mkdir(parents=True, exist_ok=True)
    best.write_binary(str(model_dir))
    return best


def run_sfm(
    images_dir: Path,
    work_dir: Path,
    image_names: list[str],
    options: ReconstructOptions,
    cameras: CamerasSpec | None = None,
    progress: Progress = no_progress,
) -> SparseModel:
    """Register ``image_names`` (files in ``images_dir``) by incremental SfM (global SfM past
    ``incremental_max_images``).

    Returns a :class:`SparseModel` in SfM's arbitrary frame and scale. Intrinsics from
    ``cameras`` are used and held fixed when given for every image. Raises
    ImagesDoNotOverlap or TooFewImagesRegistered.
    """
    pycolmap.set_random_seed(options.seed)
    sfm_dir = Path(work_dir) / "sfm"
    sfm_dir.mkdir(parents=True, exist_ok=True)
    database = sfm_dir / "database.db"
    model_dir = sfm_dir / "model"
    fixed = cameras is not None and cameras.has_all_intrinsics(image_names)
    if not (sfm_dir / "features.done").exists():
        database.unlink(missing_ok=True)
        progress("features", 0.0)
        _extract(database, images_dir, image_names, cameras, options)
        (sfm_dir / "features.done").touch()
        (sfm_dir / "matches.done").unlink(missing_ok=True)
    progress("features", 1.0)
    if not (sfm_dir / "matches.done").exists():
        progress("matching", 0.0)
        _match(database, sfm_dir, image_names, options)
        (sfm_dir / "matches.done").touch()
    progress("matching", 1.0)
    if (model_dir / "images.bin").exists():
        rec = pycolmap.Reconstruction(str(model_dir))
    else:
        progress("mapping", 0.0)
        rec = _map(database, images_dir, model_dir, len(image_names), fixed, options, progress)
    progress("mapping", 1.0)
    n_reg = rec.num_reg_images()
    if n_reg < max(2, int(np.ceil(options.min_registered_fraction * len(image_names)))):
        raise TooFewImagesRegistered(
            f"only {n_reg} of {len(image_names)} images registered (need "
            f"{options.min_registered_fraction:.0%}); take photos with more overlap"
        )
    return sparse_model_from_reconstruction(rec)


def sparse_model_from_reconstruction(rec: pycolmap.Reconstruction) -> SparseModel:
    """Convert a pycolmap reconstruction into a :class:`SparseModel` (views sorted by name)."""
    images = sorted((rec.image(i) for i in rec.reg_image_ids()), key=lambda im: im.name)
    index = {im.image_id: k for k, im in enumerate(images)}
    views = []
    for im in images:
        cam = rec.camera(im.camera_id)
        intr = intrinsics_from_colmap(
            cam.model_name, cam.width, cam.height, [float(v) for v in cam.params]
        )
        cam_from_world = np.eye(4)
        cam_from_world[:3, :] = im.cam_from_world().matrix()
        views.append(CameraView(im.name, intr, invert_rigid(cam_from_world)))
    ids = list(rec.point3D_ids())
    pts = np.zeros((len(ids), 3))
    cols = np.zeros((len(ids), 3), dtype=np.uint8)
    vis = np.zeros((len(ids), len(images)), dtype=bool)
    for n, pid in enumerate(ids):
        p = rec.point3D(pid)
        pts[n] = p.xyz
        cols[n] = p.color
        for el in p.track.elements:
            k = index.get(el.image_id)
            if k is not None:
                vis[n, k] = True
    return SparseModel(tuple(views), pts, cols, vis, float(rec.compute_mean_reprojection_error()))
