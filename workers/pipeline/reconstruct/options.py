"""Options of the reconstruct stage: one frozen dataclass and its named presets.

Each option's comment says what it is, its unit and when to change it; why each default is
what it is (the measurements) is in docs/decisions/reconstruct.md.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

from workers.pipeline.option_values import with_overrides

SgbmMode = Literal["hh4", "3way", "sgbm", "hh"]  # OpenCV StereoSGBM modes (HH4, 3WAY, SGBM, HH)


@dataclass(frozen=True)
class ReconstructOptions:
    """Every knob of the reconstruct stage. Lengths in metres, angles in degrees.

    Structure from motion (or given poses) → markers → CPU multi-view stereo: one SGBM run
    per stereo pair gives depth to both its views, far-range pairs add depths beyond
    ``far_min_depth_m``, the planar prior lays verified plane depths into far or empty
    pixels, a multi-view consistency check keeps the depths other views agree with → voxel
    fusion → ICP refinement against the previous snapshot's cloud.
    """

    preset: str = "default"  # name of the preset these options came from (recorded only)
    seed: int = 0  # RNG seed of SfM, plane RANSAC and the ICP subsample; results repeat per seed
    num_threads: int = -1  # SfM threads (-1: all cores); lower to share a machine
    min_images: int = 3  # fewer photos than this: TooFewImages (2 at the least)
    # structure from motion
    max_num_features: int = 4096  # SIFT features per image; raise for large, busy scenes
    max_image_size: int = 1600  # long side (px) images are downscaled to for SIFT; -1: as given
    exhaustive_max_images: int = 60  # exhaustive matching up to this many images, then pairs
    sequential_overlap: int = 12  # next images matched per image beyond exhaustive (+ 2^k ahead)
    loop_neighbours: int = 8  # beyond exhaustive: most similar images (retrieval) matched per image
    incremental_max_images: int = 60  # incremental SfM up to this many images, then global (GLOMAP)
    min_registered_fraction: float = 0.6  # share of images SfM must register, else it fails
    # markers
    marker_subpixel: bool = True  # refine detected ArUco corners to sub-pixel accuracy
    min_marker_views: int = 2  # views a marker must be seen in to be triangulated
    # multi-view stereo
    cuda_dense: bool = False  # pycolmap CUDA PatchMatch instead of CPU SGBM (SfM mode, CUDA builds)
    mvs_scale: float = 1.0  # image scale of the depth maps; 0.5: a quarter of the pixels, coarser
    mvs_max_image_size: int = 1152  # depth maps' long side at most (px, after mvs_scale); -1: none
    pairs_per_view: int = 1  # stereo partners per view; 2 for more complete, slower clouds
    max_disparities: int = 256  # SGBM disparity window (px); raise for deep scenes, costs time
    sgbm_block_size: int = 5  # SGBM matching block (px, odd); larger smooths, loses detail
    sgbm_mode: SgbmMode = "hh4"  # SGBM paths: "hh4" accurate, "3way" 2.5× faster, biased on slopes
    min_triangulation_angle_deg: float = 4.0  # a stereo partner's least median parallax
    max_viewing_angle_deg: float = 45.0  # a stereo partner's largest optical-axis angle
    consistency_views: int = 4  # views a depth is checked against; 6 is slower, barely better
    far_range: bool = True  # one wide-baseline pair per view for depths beyond far_min_depth_m
    far_max_axis_angle_deg: float = 30.0  # a far-range partner's largest optical-axis angle
    far_min_depth_m: float = 3.5  # where far-range depths (and their looser checks) begin
    far_max_disparities: int = 64  # far pair's SGBM window (px) below far_min_depth_m's disparity
    far_consistency_rel_tol: float = 0.03  # relative agreement needed beyond far_min_depth_m
    consistency_min_views: int = 2  # agreeing views a measured depth needs to be kept
    consistency_rel_tol: float = 0.01  # relative depth agreement needed (near depths)
    point_stride: int = 2  # every n-th pixel (rows, columns) becomes a point; 1: ~4× the points
    # planar prior (planar.py): verified plane depths for far, weakly textured floor and walls
    planar_prior: bool = True  # fill far/empty pixels with photometrically verified planes
    planar_min_depth_m: float = 3.0  # no plane depth nearer than this (the work area)
    planar_seed_stride: int = 4  # pixel stride of the consistency pass that seeds the planes
    planar_max_planes: int = 6  # most planes detected; raise for rooms with more walls
    planar_voxel_m: float = 0.03  # voxel the seed points are averaged on before RANSAC
    planar_ransac_threshold_m: float = 0.015  # RANSAC inlier distance to a plane
    planar_ransac_iterations: int = 512  # RANSAC hypotheses per plane
    planar_min_points: int = 300  # inliers (voxels) a plane needs to be kept
    planar_orthogonal_deg: float = 10.0  # planes this near ⊥ or ∥ to the first are made exactly so
    planar_manhattan_deg: float = 2.0  # walls this near one rectangular layout turn onto it; 0: off
    planar_cell_m: float = 0.25  # cell of a plane's extent grid
    planar_margin_m: float = 2.0  # how far a plane's extent reaches past its seen cells
    planar_ncc_scale: float = 0.25  # image scale of the photometric (ZNCC) check
    planar_ncc_window: int = 5  # ZNCC window (px at planar_ncc_scale)
    planar_ncc_views: int = 4  # views each plane depth is verified against
    planar_ncc_min_angle_deg: float = 1.0  # a verifying view's least triangulation angle
    planar_ncc_full_angle_deg: float = 5.0  # angle where a verifying view's weight saturates
    planar_min_views: int = 1  # verifying views that must see a pixel unoccluded
    planar_min_ncc: float = 0.8  # least mean ZNCC of an accepted plane depth
    planar_ncc_margin: float = 0.01  # ZNCC lead over depths ± planar_offset_rel it needs
    planar_offset_rel: float = 0.05  # relative depth offset of the ZNCC peak test
    planar_consistency_min_views: int = 1  # agreeing views a verified plane depth needs
    planar_reference_planes: bool = True  # the previous snapshot's planes are hypotheses too
    planar_far_row_stride: int = 1  # row stride of far plane points (point_stride elsewhere)
    # fusion
    voxel_size_m: float = 0.0025  # fusion voxel; the cloud's resolution (0: no averaging)
    # alignment to the previous snapshot
    icp_max_distances_m: tuple[float, ...] = (0.02, 0.01, 0.005)  # ICP correspondence radii
    icp_voxel_m: float = 0.008  # voxel both clouds are averaged on for ICP
    icp_max_source_points: int = 60_000  # ICP source points at most (a seeded subsample)
    max_alignment_correction_m: float = 0.05  # larger ICP translations are refused
    max_alignment_correction_deg: float = 3.0  # larger ICP rotations are refused
    min_alignment_fitness: float = 0.3  # ICP fitness below this: the correction is refused


PRESETS: dict[str, ReconstructOptions] = {
    "default": ReconstructOptions(),
    "fast": ReconstructOptions(
        preset="fast",
        max_num_features=2048,
        mvs_scale=0.5,
        max_disparities=128,
        point_stride=1,
        consistency_views=4,
        sgbm_mode="3way",
        far_range=False,  # at half scale a far pair's depth error doubles
        planar_prior=False,
    ),
    "quality": ReconstructOptions(
        preset="quality", max_num_features=8192, pairs_per_view=2, point_stride=1
    ),
}


def options_from_preset(name: str = "default", **overrides: Any) -> ReconstructOptions:
    """The named preset with ``overrides`` applied (:func:`with_overrides`); InputError for
    an unknown preset or option or a value of another type."""
    return with_overrides("reconstruct", PRESETS, name, overrides)
