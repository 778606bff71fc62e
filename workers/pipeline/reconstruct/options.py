"""Options of the reconstruct stage: one frozen dataclass and its named presets."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from workers.pipeline.errors import InputError


@dataclass(frozen=True)
class ReconstructOptions:
    """Every knob of the reconstruct stage. Lengths in metres, angles in degrees.

    Structure from motion: ``max_num_features`` SIFT features per image, images downscaled
    to ``max_image_size`` pixels on their long side for extraction (-1: as they are);
    exhaustive matching up to ``exhaustive_max_images`` images, sequential (``sequential_overlap``
    neighbours, quadratic) above. Multi-view stereo runs at ``mvs_scale`` of the image size,
    with ``pairs_per_view`` stereo partners per view; a depth survives when it agrees within
    ``consistency_rel_tol`` (relative) with ≥ ``consistency_min_views`` of the view's
    ``consistency_views`` nearest neighbours. Each stereo pair is one SGBM run that gives
    depth to both its views; with ``far_range`` each view is also in one wide-baseline pair
    for depths beyond ``far_min_depth_m``. Fusion voxel size ``voxel_size_m``, then optional
    statistical outlier removal (``sor_neighbours`` > 0); ICP refinement against the previous
    snapshot with shrinking ``icp_max_distances_m``.
    """

    preset: str = "default"
    seed: int = 0
    num_threads: int = -1
    min_images: int = 3
    # structure from motion
    max_num_features: int = 4096
    max_image_size: int = -1
    exhaustive_max_images: int = 60
    sequential_overlap: int = 12
    min_registered_fraction: float = 0.6
    # markers
    marker_subpixel: bool = True
    min_marker_views: int = 2
    # multi-view stereo
    # pycolmap's CUDA PatchMatch stereo + fusion instead of the CPU stereo below, where
    # pycolmap has CUDA and the cameras come from SfM. Opt-in: on the reconstruct bench's
    # scene (30 views 800×600, COLMAP's default PatchMatch options) it took 398 s on an H100
    # (PatchMatch 396 s at 98-100 % GPU use) for 0.58 whole-room completeness within 1 cm,
    # median 2.1 mm, p95 6.2 mm, against 34 s on this 2-core machine for 0.95, 1.35 mm,
    # 7.6 mm with the CPU stereo (bench/results/reconstruct_cuda.json, reconstruct.json)
    cuda_dense: bool = False
    mvs_scale: float = 1.0
    pairs_per_view: int = 1
    max_disparities: int = 256
    sgbm_block_size: int = 5
    # "hh4" (4 paths): ~0.03 px disparity bias on slanted surfaces; "3way" is 2.5× faster but
    # under-estimates disparity by ~0.3 px there (≈ 0.15 % too deep at 30° convergence)
    sgbm_mode: str = "hh4"
    min_triangulation_angle_deg: float = 4.0
    max_viewing_angle_deg: float = 45.0
    # 4 instead of 6 neighbours: consistency 3.7 s instead of 7.1 s (known poses, 30 views,
    # load 5-6) for completeness 0.496 vs 0.506 and the same median/p95 error
    consistency_views: int = 4
    # far-range pairs: each view is in one more pair, with the widest-baseline partner whose
    # axis is within far_max_axis_angle_deg; its SGBM window (far_max_disparities) starts at
    # far_min_depth_m and it only matches the rectified rows where the near pairs see far or
    # nothing; its depth replaces the near pairs' beyond far_min_depth_m. Known poses,
    # generated 30-view room, load 3-4: 15 more SGBM runs, far-pair SGBM time ~13 % of the
    # near pairs'; completeness 0.496 -> 0.603 (with the 3 % tolerance below; nearest camera
    # 3.5-4.5 m: 0.45 -> 0.61, > 4.5 m: 0.13 -> 0.27), median 1.32 -> 1.42 mm, p95 7.1 ->
    # 8.5 mm. 96 disparities from 3 m: 0.613, p95 8.9 mm, but far SGBM 16-20 % of the near
    # pairs'; 64 from 3 m: 0.586.
    # Axis limits 22°/26°/45° (128 from 3 m, 1 % tolerance): 0.572/0.577/0.56 vs 0.572 at
    # 30°; SGBM 3-way for these pairs: 2.6× faster but 0.549 at p95 11 mm
    far_range: bool = True
    # with known poses too: on a quiet machine (load 0.9-1.3, same run, 2 runs each) far
    # pairs took known poses from 9.6 s to 10.9 s (budget 15 s), completeness 0.496 -> 0.603.
    # (Turned off for known poses in session 3 after 13.4 -> 15.6 s measured under load 1.4-1.7.)
    # With the planar prior, each view left without a far pair of its own gets one more whose
    # depths only seed plane detection (mvs._far_seed_partners): a generated room (seed 3)
    # whose y = ±3 m walls its cameras see only along their image edges found no plane for
    # them (first capture 0.839 / 0.833 complete), with them 0.939 / 0.940.
    far_max_axis_angle_deg: float = 30.0
    far_min_depth_m: float = 3.5
    far_max_disparities: int = 64
    # the consistency tolerance beyond far_min_depth_m, where one pair's depth error is
    # 1-3 cm (z²σ/(f·b): 4.5 m, 0.8 m, σ ≈ 0.35 px measured): the kept point averages more
    # agreeing neighbours. 128 disparities from 3 m, 1 %/2 %/3 %/5 %: completeness 0.572/
    # 0.602/0.613/0.619, p95 8.4/8.8/8.9/9.0 mm; one agreeing neighbour instead of two at
    # far depths: 0.64-0.66 but p95 11.4-11.6 mm
    far_consistency_rel_tol: float = 0.03
    consistency_min_views: int = 2
    consistency_rel_tol: float = 0.01
    point_stride: int = 2
    # planar prior (planar.py, stage "planar"): planes by RANSAC from a first consistency
    # pass over every planar_seed_stride-th pixel (walls within planar_orthogonal_deg of
    # perpendicular to the first plane made exactly so: their narrow far bands fixed the
    # tilt to 2-4°), plane depths (≥ planar_min_depth_m) where SGBM has none or a far one,
    # each verified by ZNCC (quarter scale, 5×5) against up to 4 views that see the view's
    # candidate plane points (planar.coverage_views; until issue #4 the 4 widest-baseline
    # neighbours): ≥ 0.8 and a peak over depths ±5 %. Verified pixels need 1 agreeing
    # consistency neighbour (the views that verified them count too, outside the mean), far
    # ones are also taken on every row; a far SGBM depth kept because it agreed with a
    # verified plane depth falls back to it when no neighbour confirms it (the SGBM depth
    # is never replaced by the plane's while it is confirmed: no snapping). Issue #4 (every
    # case ≥ 0.90): the after capture's 0.81 was its camera path, not SfM or the ICP (its
    # true poses: 0.82): 23 % of its visible surface is seen by 2-4 views (14 % before),
    # where the widest-baseline neighbours often did not see a view's far corners, its x =
    # +3 m wall (a 2 m band at a corner) was fitted 0.57° / 14 mm off, the 0.5 m margin left
    # wall ends and floor corners without a plane, and verified pixels found no agreeing
    # consistency neighbour. Reconstruct bench, same run (load 4.4-6.2), before -> after
    # these changes: SfM + markers 0.892 -> 0.954, known poses 0.902 -> 0.941, after capture
    # 0.809 -> 0.919; median 1.40/1.49/1.46 -> 1.34/1.49/1.52 mm, p95 7.74/8.05/8.94 ->
    # 7.64/7.99/8.67 mm, points > 2 cm off 0.22/0.28/0.40 % -> 0.22/0.27/0.39 %; off: the
    # same cloud. Known poses time, alternating, 4 pairs at load 4.7-6.3: 28.6 -> 29.8 s
    # median (+4 %; 6 pairs at load 2-5: +3 %), the planar stage 1.85 -> 2.34 s. Cached depth
    # maps, after / known poses, one step at a time: view choice 0.809 -> 0.837 / 0.902 ->
    # 0.906; + Manhattan walls and 2 m margin 0.883 / 0.930; + fallback 0.897 / 0.936;
    # + verifying views as neighbours 0.918 / 0.941. Verified pixels needing no agreeing
    # neighbour at all: 0.932 / 0.959, not taken (it drops the check that keeps plane depths
    # off objects). Earlier
    # figures, reconstruct bench, same run, load
    # 3-4.4, off -> on: SfM + markers 0.599 -> 0.892, known poses 0.603 -> 0.902 (by the
    # nearest camera's distance 0.99/0.97/0.85/0.61/0.27 -> 0.99/0.98/0.99/0.96/0.74; walls
    # 0.31 -> 0.80, floor 0.71 -> 0.94), after capture 0.525 -> 0.809; known poses median
    # 1.42 -> 1.49 mm, p95 8.5 -> 8.05 mm, points > 2 cm from the true surface 0.46 % ->
    # 0.28 % (0.41 % of the 0.5 M new ones); known poses 18.7-18.8 s -> 22.4-22.8 s at that
    # load (+21 %; the planar stage 1.4 s, the rest more points: 1.26 M -> 1.86 M); at load
    # 1.2-1.5, alternating, 2 runs each: 11.0-11.7 s -> 13.0-13.3 s (+16 %). The
    # after capture's ICP follows near measured points only (stage.py): camera centres
    # 0.59 mm median (0.62 without the prior; 1.95 mm when it followed every point).
    # Steps on cached depth maps: 2 verified views and ZNCC ≥ 0.6, ±3 %, margin 0.02: 0.737;
    # 4 views, 1 needed: 0.78; margin 0.01 and ±5 %: 0.828; walls made perpendicular:
    # 0.836 (wall planes 1.5-8 mm and 2-4° off before); 1 agreeing neighbour for verified
    # pixels: 0.865 (2: 0.836); extent margin 0.5 m instead of 0.25: 0.889 (1 m: 0.921 with
    # far rows); far rows: 0.909 (every far plane pixel: 0.916 at 2.81 M points). ZNCC at
    # half scale 7×7: 0.737 vs 0.711 at a quarter, 5-8× the time. planar_snap (far SGBM
    # depths within far_consistency_rel_tol of an accepted plane take its depth): 0.940,
    # median 0.83 mm, p95 4.3 mm, but that flattens anything within 3 % (13 cm at 4.5 m)
    # onto the plane, and the generated floor and walls are exactly planar, so it flatters
    # them: off.
    # On by default since issue #4's every-case target was met (above). It was opt-in
    # while, on the scenario bench (fresh reconstructions at cff3438), the hammer in
    # 'multiple' was published flipped (76 mm / 176°): the far fill lowers the added side's
    # C2C threshold (8.7 -> 7.5 mm there) and floor around the hammer's foot tilted the pose
    # starts. The pose step's starts now take the axes of what stands above the support
    # (pose.py), which found it (1.5 mm / 1.6°) on those same reconstructions. Off in the
    # "fast" preset (half scale, no far range: not measured).
    planar_prior: bool = True
    # no plane depth nearer than this: the work area, where objects stand (≤ 2.6 m from the
    # generated cameras) keeps SGBM depths only. 0 instead: the same completeness (0.909),
    # 2.39 M instead of 1.86 M points, and median/p95 1.08/7.1 mm instead of 1.49/8.1 mm
    # only because exactly planar near floor points joined the cloud; 2.5: 0.909; 3.5: 0.881
    planar_min_depth_m: float = 3.0
    planar_seed_stride: int = 4
    planar_max_planes: int = 6
    planar_voxel_m: float = 0.03
    planar_ransac_threshold_m: float = 0.015
    planar_ransac_iterations: int = 512
    planar_min_points: int = 300
    planar_orthogonal_deg: float = 5.0
    # walls within this of one rectangular layout are turned onto it (planar.py _manhattan):
    # the after capture's x = +3 m wall, seen only in a 2 m band at its far corner, was fitted
    # 0.57° and 14 mm off (its extent's far end 4 cm); 0 = off
    planar_manhattan_deg: float = 2.0
    planar_cell_m: float = 0.25
    # how far a plane's extent reaches past the cells its seed points fill (the other planes'
    # half-spaces still bound it). Reconstruct bench, cached depth maps, with the view choice,
    # Manhattan walls and the consistency rules below, after capture / known poses:
    # 0.5 m 0.866 / 0.918, 1 m 0.900 / 0.930, 2 m 0.918 / 0.941; 2 m without the Manhattan
    # walls: 0.903 / 0.941 but 0.74 % of the after cloud > 2 cm off (0.38 % with them)
    planar_margin_m: float = 2.0
    planar_ncc_scale: float = 0.25
    planar_ncc_window: int = 5
    # verification views per view, chosen for the candidate plane points they see
    # (planar.coverage_views), their weight saturating at planar_ncc_full_angle_deg
    planar_ncc_views: int = 4
    planar_ncc_min_angle_deg: float = 1.0
    planar_ncc_full_angle_deg: float = 5.0
    planar_min_views: int = 1
    planar_min_ncc: float = 0.8
    planar_ncc_margin: float = 0.01
    planar_offset_rel: float = 0.05
    planar_snap: bool = False
    planar_consistency_min_views: int = 1
    # planes of the environment's reference cloud (the previous snapshot) are hypotheses too
    # when the new capture's own points leave them out (planar.detect_planes); still
    # verified in the new photos. A generated after capture (seed 7) that covered its
    # x = -3 m wall with SGBM depths at 17 % of its pixels found no plane there (0.876
    # whole-room completeness, that wall 0.06)
    planar_reference_planes: bool = True
    planar_far_row_stride: int = 1
    # fusion
    voxel_size_m: float = 0.0025
    # statistical outlier removal after the voxel grid (0 = off). Off by default: on the
    # generated 30-view room it removed 5 % of the work area's surface coverage and 20 % of
    # the whole room's for 0.6 mm of p95 error, at 3 s of 2-core time
    sor_neighbours: int = 0
    sor_std_ratio: float = 2.0
    # alignment to the previous snapshot
    icp_max_distances_m: tuple[float, ...] = (0.02, 0.01, 0.005)
    # 8 mm voxels, 60 k source points: 5.5-6.5 s at load 5-6 on two 1.3 M-point room clouds
    # (26 s before NumPy voxel averaging); after-capture camera centres 0.61-0.73 mm median
    # over three seeds (4 mm voxels: 0.77-0.80 mm; 20 k points: 0.60-1.92 mm, seed-dependent)
    icp_voxel_m: float = 0.008
    icp_max_source_points: int = 60_000
    max_alignment_correction_m: float = 0.05
    max_alignment_correction_deg: float = 3.0
    min_alignment_fitness: float = 0.3


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
    """The named preset with ``overrides`` applied; raises InputError for unknown names."""
    if name not in PRESETS:
        raise InputError(f"unknown reconstruct preset {name!r}; known: {', '.join(PRESETS)}")
    fields = {f.name for f in dataclasses.fields(ReconstructOptions)}
    unknown = set(overrides) - fields
    if unknown:
        raise InputError(f"unknown reconstruct options: {', '.join(sorted(unknown))}")
    kinds = {f.name: str(f.type) for f in dataclasses.fields(ReconstructOptions)}
    checked = {k: _checked_value(k, v, kinds[k]) for k, v in overrides.items()}
    return dataclasses.replace(PRESETS[name], **checked)


def _checked_value(name: str, value: Any, kind: str) -> Any:
    """``value`` as the option's type (an int is taken for a float, a list for a tuple of
    floats); raises InputError naming the option when it is of another type."""
    number = isinstance(value, int | float) and not isinstance(value, bool)
    if kind == "bool" and isinstance(value, bool):
        return value
    if kind == "int" and number and float(value).is_integer():
        return int(value)
    if kind == "float" and number:
        return float(value)
    if kind == "str" and isinstance(value, str):
        return value
    is_tuple = kind.startswith("tuple[float")
    if (
        is_tuple
        and isinstance(value, list | tuple)
        and all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
    ):
        return tuple(float(v) for v in value)
    if kind not in ("bool", "int", "float", "str") and not is_tuple:
        return value
    expected = "a list of numbers" if is_tuple else f"a {kind}"
    raise InputError(f"reconstruct option {name} must be {expected}, got {value!r}")
