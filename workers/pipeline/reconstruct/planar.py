"""Planar prior for far, weakly textured surfaces (floor, walls), as in planar-prior MVS
(ACMP, Xu & Tao 2020), on top of the SGBM depth maps.

1. :func:`detect_planes`: a few dominant planes by seeded RANSAC over reliable points
   (those that passed the multi-view consistency check), then over the environment's
   previous cloud where it has planes those points leave out, walls made exactly perpendicular
   to the first plane and turned onto one rectangular layout when that close to it, each
   with the cells of a 2-D grid in its own coordinates where it was seen, so a plane is not
   extended past its points beyond ``planar_margin_m``, nor across another plane where it
   was not seen beyond it (a floor stops at the wall it meets: just behind the wall the
   floor plane is close enough to the wall's depth to pass the photometric test, and it is
   not there).
2. :func:`fill_depths`: in each view, a pixel with no SGBM depth or a depth beyond
   ``far_min_depth_m`` takes the depth of the nearest plane its ray hits inside that
   plane's extent, but only when that depth is photometrically verified: the reference
   patch's ZNCC against the views that see the view's candidate plane points
   (:func:`coverage_views`), sampled through the plane point, beats the ZNCC at depths
   ``planar_offset_rel`` nearer and farther along the ray, and is high. Views whose own
   depth map sees something in front of the plane point are skipped (occlusion), and a
   pixel near a nearer SGBM depth of its own view keeps no plane depth.

The filled depth maps then go through the same consistency filter and fusion as the
SGBM ones, where the views that verified a view's plane depths count as agreeing
neighbours too, and a far SGBM depth kept because it agreed with a verified plane depth
falls back to that depth when no neighbour confirms it. Everything is in the env frame,
metres, OpenCV camera axes.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from workers.pipeline.errors import ShapeError
from workers.pipeline.geometry import as_points
from workers.pipeline.reconstruct.common import Progress, no_progress
from workers.pipeline.reconstruct.fusion import voxel_average
from workers.pipeline.reconstruct.mvs import DenseView, VerifiedDepths, WindowStats, zncc
from workers.pipeline.reconstruct.options import ReconstructOptions

FloatArray = NDArray[np.float64]
F32 = NDArray[np.float32]


@dataclass(frozen=True)
class Plane:
    """A plane n·X = ``offset_m`` in the env frame (``normal_env`` (3,) unit) and where it
    was seen: ``occupied`` (U, V) bool cells of ``cell_m`` in the plane's own coordinates
    u = (X − ``origin_env``)·``axes_env``[0], v = …·``axes_env``[1], cell (0, 0) starting at
    ``lo_uv`` (2,) metres, already grown by the margin;
    ``limits_env`` the other planes' half-spaces it keeps to and ``beyond`` the cells where
    it was seen past them (see :meth:`contains`). ``inliers``: supporting points."""

    normal_env: FloatArray
    offset_m: float
    origin_env: FloatArray
    axes_env: FloatArray
    lo_uv: FloatArray
    cell_m: float
    occupied: NDArray[np.bool_]
    inliers: int
    beyond: NDArray[np.bool_] | None = None
    limits_env: FloatArray = field(default_factory=lambda: np.zeros((0, 4)))

    def contains(self, points_env: FloatArray) -> NDArray[np.bool_]:
        """(N,) whether (N, 3) env points (assumed on the plane) fall in its extent: an
        ``occupied`` cell, where the point also keeps to the side of every other plane that
        this plane's inliers are on (``limits_env`` (K, 4) rows a, b: a·X ≤ b), unless the
        cell is within the margin of inliers beyond those limits (``beyond``). So a floor
        stops at a wall it meets (the cells along their junction and the margin go no
        further) and a wall at the floor, while a floor seen on both sides of a machine's
        face goes on."""
        ij = self.cell_index(points_env)
        gu, gv = self.occupied.shape
        inside = (ij[:, 0] >= 0) & (ij[:, 0] < gu) & (ij[:, 1] >= 0) & (ij[:, 1] < gv)
        out = np.zeros(len(points_env), np.bool_)
        cells = ij[inside, 0], ij[inside, 1]
        out[inside] = self.occupied[cells]
        if self.beyond is not None and len(self.limits_env):
            within = np.all(
                points_env[inside] @ self.limits_env[:, :3].T <= self.limits_env[:, 3], axis=1
            )
            out[inside] &= self.beyond[cells] | within
        return out

    def cell_index(self, points_env: FloatArray) -> NDArray[np.int64]:
        """(N, 2) grid cell (i, j) of (N, 3) env points (assumed on the plane); may lie
        outside the grid."""
        return _cell_index(points_env, self.origin_env, self.axes_env, self.lo_uv, self.cell_m)

    def to_json(self) -> dict[str, Any]:
        return {
            "normal": [round(float(v), 5) for v in self.normal_env],
            "offset_m": round(self.offset_m, 5),
            "inliers": self.inliers,
            "area_m2": round(float(self.occupied.sum()) * self.cell_m**2, 2),
        }


def _fit(points: FloatArray) -> tuple[FloatArray, float]:
    """Least-squares plane (unit normal, offset) of (N, 3) points, N ≥ 3."""
    centre = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centre, full_matrices=False)
    normal = vt[2] / np.linalg.norm(vt[2])
    return normal, float(normal @ centre)


def _near_copy(normals: FloatArray, offsets: FloatArray, plane: Plane) -> NDArray[np.bool_]:
    """(K,) whether planes of (K, 3) unit normals and (K,) offsets (m) lie within 10° and
    10 cm of ``plane``."""
    cos = normals @ plane.normal_env
    return np.asarray(
        (np.abs(cos) > np.cos(np.radians(10.0)))
        & (np.abs(offsets - plane.offset_m * np.sign(cos)) < 0.1)
    )


def _snapped_normals(
    normals: FloatArray, up: FloatArray, max_deg: float
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """(K, 3) unit normals, those within ``max_deg`` of perpendicular to the unit ``up`` made
    exactly perpendicular, those within it of parallel made ±``up``; and (K,) which were."""
    cos_up = normals @ up
    out = normals.copy()
    perp = np.abs(cos_up) <= np.sin(np.radians(max_deg))
    wall = normals[perp] - cos_up[perp, None] * up
    out[perp] = wall / np.linalg.norm(wall, axis=1, keepdims=True)
    level = np.abs(cos_up) >= np.cos(np.radians(max_deg))
    out[level] = np.sign(cos_up[level])[:, None] * up
    return out, perp | level


def _ransac(
    points: FloatArray,
    threshold_m: float,
    iterations: int,
    rng: np.random.Generator,
    up: FloatArray | None = None,
    snap_deg: float = 0.0,
    taken: tuple[Plane, ...] = (),
) -> tuple[FloatArray, float, NDArray[np.bool_]]:
    """Best plane of (N, 3) points by inlier count over ``iterations`` random triples,
    refitted twice by least squares on its inliers; (normal, offset, inlier mask).

    With ``up`` (the first plane's unit normal) every other hypothesis is instead the plane
    through a random pair of points that contains ``up`` (a wall), and every hypothesis
    within ``snap_deg`` of perpendicular or parallel to ``up`` is made exactly so before its
    inliers are counted (as :func:`_orthogonalise` makes the plane found). A wall seen only
    in a low band along its foot (10-30 cm of a 6 m wall, from the image edges) gives
    triples that tilt it, and it lost to a plane 4° off level through the feet of several
    walls and stray floor points, which counts few inliers once level. Hypotheses that are
    near copies of a plane in ``taken`` (:func:`_near_copy`) are not counted: the floor's
    noise 3-6 cm above it outcounted such a wall band, and removing it took the band's foot."""
    # hypotheses are scored on at most 4096 of the points (the counts only rank them)
    sample = points[rng.permutation(len(points))[:4096]] if len(points) > 4096 else points
    best_count = -1
    best_plane = (np.array([0.0, 0.0, 1.0]), 0.0)
    batch = 128
    for n_batch, start in enumerate(range(0, iterations, batch)):
        k = min(batch, iterations - start)
        tri = sample[rng.integers(0, len(sample), size=(k, 3))]
        if up is not None and n_batch % 2 == 1:
            normals = np.cross(tri[:, 1] - tri[:, 0], up)
        else:
            normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        norm = np.linalg.norm(normals, axis=1)
        ok = norm > 1e-9
        if not ok.any():
            continue
        normals = normals[ok] / norm[ok, None]
        if up is not None and snap_deg > 0:
            normals, _ = _snapped_normals(normals, up, snap_deg)
        offsets = np.sum(normals * tri[ok, 0], axis=1)
        counts = (np.abs(sample @ normals.T - offsets) <= threshold_m).sum(axis=0)
        for plane in taken:
            counts[_near_copy(normals, offsets, plane)] = -1
        j = int(np.argmax(counts))
        if counts[j] > best_count:
            best_count, best_plane = int(counts[j]), (normals[j], float(offsets[j]))
    normal, offset = best_plane
    best = np.abs(points @ normal - offset) <= threshold_m
    if best.sum() < 3:
        return normal, offset, best
    normal, offset = _fit(points[best])
    for _ in range(2):
        best = np.abs(points @ normal - offset) <= threshold_m
        normal, offset = _fit(points[best])
    return normal, offset, best


def _orthogonalise(
    points: FloatArray,
    normal: FloatArray,
    inliers: NDArray[np.bool_],
    first_normal: FloatArray,
    max_deg: float,
    threshold_m: float,
) -> tuple[FloatArray, float, NDArray[np.bool_]]:
    """A plane within ``max_deg`` of perpendicular to the first (largest) plane made exactly
    perpendicular (a wall on a floor), one within ``max_deg`` of parallel to it made exactly
    parallel (a table top), each with its offset the median over its inliers, which are
    recounted; any other plane is returned as it is. A narrow band of far, noisy points
    (a wall's lower edge) fixes a plane's tilt about the band poorly (2-7° measured); the
    perpendicular is the better estimate when the fitted plane is that close to it. A plane
    a few degrees off the floor through the lower edges of several walls and stray floor
    points (found in a generated room) keeps few inliers once made level."""
    snapped_all, was_snapped = _snapped_normals(normal[None], first_normal, max_deg)
    if not was_snapped[0]:
        return normal, float(np.median(points[inliers] @ normal)), inliers
    snapped = snapped_all[0]
    offset = float(np.median(points[inliers] @ snapped))
    inl = np.abs(points @ snapped - offset) <= threshold_m
    if not inl.any():
        return snapped, offset, inl
    offset = float(np.median(points[inl] @ snapped))
    return snapped, offset, inl


def _cell_index(
    points_env: FloatArray, origin: FloatArray, axes: FloatArray, lo_uv: FloatArray, cell_m: float
) -> NDArray[np.int64]:
    """(N, 2) cell (i, j) of (N, 3) points in a plane's grid: u, v = (X − origin)·axes,
    cell (0, 0) starting at ``lo_uv``."""
    uv = (points_env - origin) @ axes.T
    return np.floor((uv - lo_uv) / cell_m).astype(np.int64)


def _margin_cells(margin_m: float, cell_m: float) -> int:
    return int(np.ceil(margin_m / cell_m))


def _mark_cells(ij: NDArray[np.int64], shape: tuple[int, ...], grow: int) -> NDArray[np.bool_]:
    """(U, V) bool grid with the cells ``ij`` (N, 2) set, dilated by ``grow`` cells."""
    grid = np.zeros(shape, np.uint8)
    grid[ij[:, 0], ij[:, 1]] = 1
    if grow > 0:
        grid = np.asarray(cv2.dilate(grid, np.ones((2 * grow + 1, 2 * grow + 1), np.uint8)))
    return grid.astype(np.bool_)


def _extent(
    points_env: FloatArray, normal: FloatArray, offset: float, cell_m: float, margin_m: float
) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.bool_]]:
    """Plane coordinates and seen cells of the inliers (N, 3): (origin, axes (2, 3), lo_uv,
    occupied) with the occupied cells grown by ``margin_m``."""
    origin = normal * offset
    helper = np.eye(3)[int(np.argmin(np.abs(normal)))]
    axis_u = np.cross(normal, helper)
    axis_u /= np.linalg.norm(axis_u)
    axes = np.stack([axis_u, np.cross(normal, axis_u)])
    uv = (points_env - origin) @ axes.T
    grow = _margin_cells(margin_m, cell_m)
    lo = np.floor(uv.min(axis=0) / cell_m) * cell_m - grow * cell_m
    ij = _cell_index(points_env, origin, axes, lo, cell_m)
    shape = ij.max(axis=0) + 1 + grow
    return origin, axes, lo, _mark_cells(ij, (int(shape[0]), int(shape[1])), grow)


def detect_planes(
    points_env: FloatArray, options: ReconstructOptions, reference_env: FloatArray | None = None
) -> list[Plane]:
    """Up to ``planar_max_planes`` dominant planes of (N, 3) reliable env points (metres),
    then of the environment's (M, 3) ``reference_env`` cloud where given.

    The points are first averaged on a ``planar_voxel_m`` grid (even density). Each round
    RANSAC (``planar_ransac_iterations`` triples, seeded by ``options.seed``, inliers within
    ``planar_ransac_threshold_m``) takes the plane with the most points, refitted by least
    squares; it is kept when it has ≥ ``planar_min_points`` inliers and is not a near copy
    (within 10° and 10 cm) of one already kept, and the points within twice the threshold
    are removed before the next round. After the first plane, with
    ``planar_orthogonal_deg`` > 0, hypotheses and planes within that angle of perpendicular
    or parallel to it are made exactly so (walls and level surfaces on a floor; see
    :func:`_ransac`), and a plane that keeps too few inliers so is dropped. The reference
    cloud's points that the planes found so far explain are removed and the rounds go on
    over the rest: a wall the new capture saw too little of for a plane (a 17 % SGBM cover
    of it in a generated after capture) is still a hypothesis, with the extent where the
    reference saw it; :func:`fill_depths` still verifies every plane depth in the new
    photos. Each plane then keeps to the side of every other plane that its inliers are on,
    except in cells where it was seen beyond.
    Fewer than ``planar_min_points`` points: no planes from them.
    Raises ShapeError when ``points_env`` or ``reference_env`` is not (N, 3).
    """
    rng = np.random.default_rng(options.seed)
    thr = options.planar_ransac_threshold_m
    planes: list[Plane] = []
    members: list[FloatArray] = []
    for name, cloud in (("points_env", points_env), ("reference_env", reference_env)):
        if cloud is None:
            continue
        pts = as_points(cloud, name)
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        if len(pts) == 0:
            continue
        rest, _ = voxel_average(pts, options.planar_voxel_m)
        for p in planes:
            rest = rest[np.abs(rest @ p.normal_env - p.offset_m) > 2.0 * thr]
        _find_planes(rest, planes, members, rng, options)
    if options.planar_manhattan_deg > 0:
        planes, members = _manhattan(planes, members, options)
    margin = options.planar_margin_m
    return [
        _with_limits(p, m, planes, 2.0 * thr, margin) for p, m in zip(planes, members, strict=True)
    ]


def _find_planes(
    rest: FloatArray,
    planes: list[Plane],
    members: list[FloatArray],
    rng: np.random.Generator,
    options: ReconstructOptions,
) -> None:
    """RANSAC rounds over (N, 3) voxel-averaged points ``rest`` (see :func:`detect_planes`),
    appending each plane kept to ``planes`` and its inliers to ``members``."""
    thr = options.planar_ransac_threshold_m
    for _ in range(4 * options.planar_max_planes):
        if len(planes) >= options.planar_max_planes or len(rest) < options.planar_min_points:
            break
        up = planes[0].normal_env if planes and options.planar_orthogonal_deg > 0 else None
        normal, offset, inl = _ransac(
            rest,
            thr,
            options.planar_ransac_iterations,
            rng,
            up,
            options.planar_orthogonal_deg,
            tuple(planes),
        )
        if inl.sum() < options.planar_min_points:
            break
        # the refit may drift onto a plane already kept, or hold together only tilted
        keep = not any(_near_copy(normal[None], np.array([offset]), p)[0] for p in planes)
        if keep and up is not None:
            snapped = _orthogonalise(rest, normal, inl, up, options.planar_orthogonal_deg, thr)
            keep = int(snapped[2].sum()) >= options.planar_min_points
            if keep:
                normal, offset, inl = snapped
        if keep:
            origin, axes, lo, occ = _extent(
                rest[inl], normal, offset, options.planar_cell_m, options.planar_margin_m
            )
            planes.append(
                Plane(normal, offset, origin, axes, lo, options.planar_cell_m, occ, int(inl.sum()))
            )
            members.append(rest[inl])
        rest = rest[np.abs(rest @ normal - offset) > 2.0 * thr]


def _manhattan(
    planes: list[Plane], members: list[FloatArray], options: ReconstructOptions
) -> tuple[list[Plane], list[FloatArray]]:
    """Walls (planes exactly perpendicular to the first plane) within
    ``planar_manhattan_deg`` of one common rectangular layout turned onto it: their
    directions about the first plane's normal, taken modulo 90°, are averaged (each weighed
    by N·var of its inliers along it, the inverse variance of a fitted line's direction, so
    a short band hardly moves the layout), each such wall gets the nearest multiple of 90°
    from that mean and its offset becomes the median over its inliers, which are then
    recounted within the RANSAC threshold (its extent too). A wall seen only in a short,
    far band (a corner at 4-5 m) tilts by 0.3-0.6° about the vertical, which its
    extrapolated far end turns into 1.5-4 cm; the other walls fix its direction far better.
    Fewer than two walls: unchanged."""
    if len(planes) < 3:
        return planes, members
    up = planes[0].normal_env
    walls = [k for k in range(1, len(planes)) if abs(float(planes[k].normal_env @ up)) < 1e-9]
    if len(walls) < 2:
        return planes, members
    e1 = planes[walls[0]].normal_env
    e2 = np.cross(up, e1)
    ang = np.array(
        [np.arctan2(planes[k].normal_env @ e2, planes[k].normal_env @ e1) for k in walls]
    )
    # each wall's direction weighs by N·var of its inliers along it (the inverse variance of
    # a fitted line's direction): a long wall fixes the layout, a short band hardly moves it
    weight = np.array(
        [np.var(members[k] @ np.cross(up, planes[k].normal_env)) * len(members[k]) for k in walls]
    )
    # modulo 90°: the mean of the angles × 4 on the circle
    mean = float(np.angle(np.sum(weight * np.exp(4j * ang)))) / 4.0
    thr = options.planar_ransac_threshold_m
    out_planes, out_members = list(planes), list(members)
    for k, a in zip(walls, ang, strict=True):
        quarter = np.round((a - mean) / (np.pi / 2))
        off = a - mean - quarter * np.pi / 2
        if abs(off) > np.radians(options.planar_manhattan_deg):
            continue
        t = mean + quarter * np.pi / 2
        normal = np.cos(t) * e1 + np.sin(t) * e2
        normal /= np.linalg.norm(normal)
        pts = members[k]
        offset = float(np.median(pts @ normal))
        inl = pts[np.abs(pts @ normal - offset) <= thr]
        if len(inl) < 3:
            continue
        offset = float(np.median(inl @ normal))
        origin, axes, lo, occ = _extent(
            inl, normal, offset, options.planar_cell_m, options.planar_margin_m
        )
        out_planes[k] = Plane(
            normal, offset, origin, axes, lo, options.planar_cell_m, occ, len(inl)
        )
        out_members[k] = inl
    return out_planes, out_members


def _with_limits(
    plane: Plane, inliers_env: FloatArray, planes: list[Plane], tol_m: float, margin_m: float
) -> Plane:
    """``plane`` with the half-spaces it keeps to: for every other plane, the side that its
    (N, 3) ``inliers_env`` lie on (their mean's side); and the cells where it may cross
    them: those holding inliers more than ``tol_m`` beyond one, grown by ``margin_m``."""
    centre = inliers_env.mean(axis=0)
    rows = []
    for other in planes:
        if other is plane:
            continue
        side = float(other.normal_env @ centre) - other.offset_m
        if abs(side) < tol_m:
            continue
        sign = np.sign(side)  # keep sign·(n·X − d) ≥ 0, i.e. −sign·n·X ≤ −sign·d
        rows.append([*(-sign * other.normal_env), -sign * other.offset_m])
    limits = np.asarray(rows, np.float64).reshape(-1, 4)
    out = inliers_env[np.any(inliers_env @ limits[:, :3].T > limits[:, 3] + tol_m, axis=1)]
    grow = _margin_cells(margin_m, plane.cell_m)
    beyond = _mark_cells(plane.cell_index(out), plane.occupied.shape, grow)
    return replace(plane, beyond=beyond, limits_env=limits)


def _rays_cam(k_matrix: FloatArray, width: int, height: int) -> NDArray[np.float32]:
    """(3, H, W) float32 camera-frame rays K⁻¹ (x, y, 1) of every pixel (z = 1)."""
    k = k_matrix
    xs = ((np.arange(width) - k[0, 2]) / k[0, 0]).astype(np.float32)
    ys = ((np.arange(height) - k[1, 2]) / k[1, 1]).astype(np.float32)
    out = np.ones((3, height, width), np.float32)
    out[0] = xs[None, :]
    out[1] = ys[:, None]
    return out


def _linear(rays: NDArray[np.float32], coeffs: FloatArray) -> NDArray[np.float32]:
    """(H, W) float32 c · r of (3, H, W) rays and a (3,) vector (linear in the pixel)."""
    a, b, c = (float(v) for v in coeffs)
    return np.asarray(a * rays[0] + (b * rays[1] + np.float32(c)), np.float32)


def _ray_depth(
    rays: NDArray[np.float32], env_from_cam: FloatArray, plane: Plane
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """(H, W) camera depth z where each ray of (3, H, W) ``rays`` (z = 1) from a camera at
    ``env_from_cam`` (4, 4) meets ``plane`` (inf or negative: no hit in front), and the
    denominator (Rᵀn)·r (its cosine to the normal times the ray's length)."""
    denom = _linear(rays, env_from_cam[:3, :3].T @ plane.normal_env)
    numer = np.float32(plane.offset_m - float(plane.normal_env @ env_from_cam[:3, 3]))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.asarray(numer / denom, np.float32), denom


def plane_depths(
    view: DenseView,
    planes: list[Plane],
    min_cos_incidence: float = 0.1,
    k_matrix: FloatArray | None = None,
    size: tuple[int, int] | None = None,
    beyond: F32 | None = None,
) -> tuple[F32, NDArray[np.int16]]:
    """Camera depth (H, W) float32 metres (0 = no hit) of the nearest plane each pixel's ray
    hits inside that plane's extent, and which plane (int16, −1 = none). The grid is the
    view's own unless ``k_matrix`` (3, 3) and ``size`` (W, H) give a rescaled one. Hits
    where the ray meets the plane at more than arccos(``min_cos_incidence``) from its normal
    are ignored (grazing: the depth is too sensitive to the plane), and so are hits not
    farther than ``beyond`` (H, W) float32 metres where given (the planes behind those).

    With r = K⁻¹ (x, y, 1) and R, C the view's env_from_cam rotation and centre, the ray
    C + z R r meets n·X = d at camera depth z = (d − n·C) / ((Rᵀn)·r).
    """
    w, h = view.size if size is None else size
    rays = _rays_cam(view.k_matrix if k_matrix is None else k_matrix, w, h)
    rot = view.env_from_cam[:3, :3]
    centre = view.env_from_cam[:3, 3]
    length = np.sqrt(rays[0] ** 2 + rays[1] ** 2 + 1.0)
    depth = np.full((h, w), np.inf, np.float32)
    label = np.full((h, w), -1, np.int16)
    for idx, p in enumerate(planes):
        z, denom = _ray_depth(rays, view.env_from_cam, p)
        ok = (z > 0) & (np.abs(denom) >= min_cos_incidence * length) & (z < depth)
        if beyond is not None:
            ok &= z > beyond
        ys, xs = np.nonzero(ok)
        if len(ys) == 0:
            continue
        hit = centre + (rays[:, ys, xs] * z[ys, xs]).T.astype(np.float64) @ rot.T
        inside = p.contains(hit)
        depth[ys[inside], xs[inside]] = z[ys[inside], xs[inside]]
        label[ys[inside], xs[inside]] = idx
    return np.where(np.isfinite(depth), depth, 0.0).astype(np.float32), label


def _label_depths(view: DenseView, planes: list[Plane], label: NDArray[np.int16]) -> F32:
    """Camera depth (H, W) float32 metres of each pixel's plane ``label`` (−1: 0) on the
    view's own grid, with no extent test (the labels come from :func:`plane_depths`)."""
    w, h = view.size
    depth = np.zeros((h, w), np.float32)
    rays = _rays_cam(view.k_matrix, w, h)
    for idx, p in enumerate(planes):
        sel = label == idx
        if not sel.any():
            continue
        z, _ = _ray_depth(rays, view.env_from_cam, p)
        depth[sel] = np.where(z[sel] > 0, z[sel], 0.0)
    return depth


def _gray(view: DenseView, scale: float) -> F32:
    g = cv2.cvtColor(view.image, cv2.COLOR_BGR2GRAY).astype(np.float32)
    if scale != 1.0:
        w, h = view.size
        size = (round(w * scale), round(h * scale))
        g = np.asarray(cv2.resize(g, size, interpolation=cv2.INTER_AREA), np.float32)
    return np.asarray(g, np.float32)


def _scaled_k(k_matrix: FloatArray, scale: float) -> FloatArray:
    k = k_matrix.copy()
    k[0, 0] *= scale
    k[1, 1] *= scale
    k[0, 2] = (k[0, 2] + 0.5) * scale - 0.5
    k[1, 2] = (k[1, 2] + 0.5) * scale - 0.5
    return k


def _check_views(views: list[DenseView], depths: list[F32]) -> None:
    n = len(views)
    if len(depths) != n:
        raise ShapeError(f"{n} views but {len(depths)} depth maps")
    for v, d in zip(views, depths, strict=True):
        if d.shape != v.image.shape[:2]:
            raise ShapeError(f"{v.name}: depth map {d.shape}, image {v.image.shape[:2]}")


@dataclass(frozen=True)
class ViewChoice:
    """How :func:`coverage_views` chooses verifying views: at most ``count`` of them, seeing
    a point whole ``window``-pixel windows inside their grid, under a triangulation angle of
    at least ``min_angle_deg``, a view's weight saturating at ``full_angle_deg``."""

    count: int
    window: int
    min_angle_deg: float = 1.0
    full_angle_deg: float = 5.0

    @classmethod
    def from_options(cls, options: ReconstructOptions) -> ViewChoice:
        return cls(
            options.planar_ncc_views,
            options.planar_ncc_window,
            options.planar_ncc_min_angle_deg,
            options.planar_ncc_full_angle_deg,
        )


@dataclass(frozen=True)
class _ScaledViews:
    """Every view on the ZNCC grid (``planar_ncc_scale`` of its size): (h, w) float32 grey
    images, (3, 3) scaled K, and (h, w) float32 depth maps in metres (0 = unknown,
    nearest-neighbour downscaled)."""

    grays: list[F32]
    k_matrices: list[FloatArray]
    depths: list[F32]


def _scaled_views(views: list[DenseView], depths: list[F32], scale: float) -> _ScaledViews:
    grays = [_gray(v, scale) for v in views]
    small_depths = [
        np.asarray(
            cv2.resize(d, (g.shape[1], g.shape[0]), interpolation=cv2.INTER_NEAREST), np.float32
        )
        for d, g in zip(depths, grays, strict=True)
    ]
    return _ScaledViews(grays, [_scaled_k(v.k_matrix, scale) for v in views], small_depths)


@dataclass(frozen=True)
class _Candidates:
    """View ``index``'s candidate plane depths on the ZNCC grid: ``depth`` (h, w) float32
    metres of the nearest plane inside its extent beyond the depths already tried (0: none),
    ``label`` (h, w) int16 which plane (−1: none), ``mask`` (h, w) bool the pixels that may
    take it (plane depth ≥ ``planar_min_depth_m``, own depth none or ≥ ``far_min_depth_m``)."""

    index: int
    depth: F32
    label: NDArray[np.int16]
    mask: NDArray[np.bool_]


def _candidates(
    i: int,
    view: DenseView,
    planes: list[Plane],
    scaled: _ScaledViews,
    options: ReconstructOptions,
    beyond: F32,
) -> _Candidates:
    hs, ws = scaled.grays[i].shape
    plane_s, label_s = plane_depths(
        view, planes, k_matrix=scaled.k_matrices[i], size=(ws, hs), beyond=beyond
    )
    own_s = scaled.depths[i]
    cand_s = (plane_s >= options.planar_min_depth_m) & (
        (own_s <= 0) | (own_s >= options.far_min_depth_m)
    )
    return _Candidates(i, plane_s, label_s, cand_s)


def _choose_views(
    cands: _Candidates,
    views: list[DenseView],
    scaled: _ScaledViews,
    options: ReconstructOptions,
    samples: int = 1000,
) -> tuple[int, ...]:
    """:func:`coverage_views` for view ``cands.index``'s candidate pixels (a strided subset of
    at most about ``samples`` of them) at their plane depths on the scaled grid."""
    i = cands.index
    plane_s = cands.depth
    ys, xs = np.nonzero(cands.mask & (plane_s > 0))
    step = max(1, len(ys) // samples)
    ys, xs = ys[::step], xs[::step]
    k = scaled.k_matrices[i]
    z = plane_s[ys, xs].astype(np.float64)
    p_cam = np.stack([(xs - k[0, 2]) / k[0, 0] * z, (ys - k[1, 2]) / k[1, 1] * z, z], axis=1)
    env = views[i].env_from_cam
    pts = p_cam @ env[:3, :3].T + env[:3, 3]
    choice = ViewChoice.from_options(options)
    return coverage_views(i, views, pts, scaled.depths, scaled.k_matrices, choice)


def coverage_views(
    i: int,
    views: list[DenseView],
    points_env: FloatArray,
    depths: list[F32],
    k_matrices: list[FloatArray],
    choice: ViewChoice,
) -> tuple[int, ...]:
    """Up to ``choice.count`` views to verify view ``i``'s plane points (N, 3, env metres)
    against, chosen greedily: each time the view that sees the most of the points that fewer
    than two chosen views see, each point counted with the weight min(sin θ / sin
    ``choice.full_angle_deg``, 1) of its triangulation angle θ between the two views (none
    below ``choice.min_angle_deg``).

    A view sees a point when it projects ≥ ``choice.window`` // 2 pixels inside its grid (K
    of ``k_matrices``, size of ``depths``) in front of it and its ``depths`` map there has
    nothing nearer than 0.97 × the point's depth. A view that sees none: not chosen. Views
    that see the plane at a similar scale and foreshortening suit the quarter-scale ZNCC
    better than the widest baselines (docs/decisions/reconstruct.md). Raises ShapeError for
    bad shapes.
    """
    points_env = as_points(points_env, "points_env")
    if len(depths) != len(views) or len(k_matrices) != len(views):
        raise ShapeError(f"{len(views)} views, {len(depths)} depth maps, {len(k_matrices)} K")
    weight = np.zeros((len(views), len(points_env)), np.float64)
    for j in range(len(views)):
        if j != i:
            weight[j] = _coverage_weight(
                views[i], views[j], points_env, depths[j], k_matrices[j], choice
            )
    chosen: list[int] = []
    covered = np.zeros(len(points_env), np.int32)
    for _ in range(choice.count):
        gain = (weight * (covered < 2)).sum(axis=1)
        gain[chosen] = -1.0
        j = int(np.argmax(gain))
        if gain[j] <= 0:
            break
        chosen.append(j)
        covered += weight[j] > 0
    return tuple(chosen)


def _coverage_weight(
    view_i: DenseView,
    view: DenseView,
    points_env: FloatArray,
    depth: F32,
    k: FloatArray,
    choice: ViewChoice,
) -> FloatArray:
    """(N,) weight of ``view`` (grid K ``k``, depth map ``depth``) for verifying view_i's
    (N, 3) env points: 0 where it does not see them (see :func:`coverage_views`)."""
    centre_i = view_i.env_from_cam[:3, 3]
    to_i = centre_i - points_env
    to_i /= np.maximum(np.linalg.norm(to_i, axis=1, keepdims=True), 1e-12)
    half = choice.window // 2
    sin_full = np.sin(np.radians(choice.full_angle_deg))
    cam = view.cam_from_env
    p = points_env @ cam[:3, :3].T + cam[:3, 3]
    h, w = depth.shape
    with np.errstate(divide="ignore", invalid="ignore"):
        u = k[0, 0] * p[:, 0] / p[:, 2] + k[0, 2]
        v = k[1, 1] * p[:, 1] / p[:, 2] + k[1, 2]
    ok = (p[:, 2] > 0) & (u >= half) & (u <= w - 1 - half) & (v >= half) & (v <= h - 1 - half)
    seen = np.zeros(len(p), np.float32)
    seen[ok] = depth[np.rint(v[ok]).astype(np.int64), np.rint(u[ok]).astype(np.int64)]
    ok &= ~((seen > 0) & (seen < 0.97 * p[:, 2]))
    to_j = view.env_from_cam[:3, 3] - points_env
    to_j /= np.maximum(np.linalg.norm(to_j, axis=1, keepdims=True), 1e-12)
    sin = np.linalg.norm(np.cross(to_i, to_j), axis=1)
    ok &= sin >= np.sin(np.radians(choice.min_angle_deg))
    return np.asarray(np.where(ok, np.minimum(sin / sin_full, 1.0), 0.0), np.float64)


@dataclass(frozen=True)
class PlaneFill:
    """What :func:`fill_depths` gives, one entry per view.

    ``depths`` (H, W) float32 metres (0 = unknown) with the verified plane depths laid in;
    ``from_plane`` (H, W) bool: the pixels whose depth now comes from a plane;
    ``fallback`` (H, W) float32 metres: the verified plane depth of the pixels that keep
    their own far SGBM depth because it agreed with it (0 elsewhere), for when that depth
    fails the consistency check (:func:`~workers.pipeline.reconstruct.mvs.consistent_points_split`);
    ``checked_by``: the views its plane depths were verified against; ``stats``: the
    planes, pixels filled, far depths replaced.
    """

    depths: list[F32]
    from_plane: list[NDArray[np.bool_]]
    fallback: list[F32]
    checked_by: list[tuple[int, ...]]
    stats: dict[str, Any]

    def verified(self) -> VerifiedDepths:
        """The plane depths as the consistency check's verified depths."""
        return VerifiedDepths(self.from_plane, self.checked_by, self.fallback)


@dataclass(frozen=True)
class _ViewFill:
    """One view's share of a :class:`PlaneFill`, with its pixel counts."""

    depth: F32
    from_plane: NDArray[np.bool_]
    fallback: F32
    checked_by: tuple[int, ...]
    filled: int
    replaced: int

    @classmethod
    def unchanged(cls, depth: F32, checked_by: tuple[int, ...]) -> _ViewFill:
        no_fallback = np.zeros(depth.shape, np.float32)
        return cls(depth.copy(), np.zeros(depth.shape, np.bool_), no_fallback, checked_by, 0, 0)


def fill_depths(
    views: list[DenseView],
    depths: list[F32],
    planes: list[Plane],
    options: ReconstructOptions,
    progress: Progress = no_progress,
) -> PlaneFill:
    """Depth maps (each (H, W) float32 metres, 0 = unknown) with verified plane depths laid
    into the pixels that have no SGBM depth or one ≥ ``far_min_depth_m`` (see
    :class:`PlaneFill`).

    The test runs on a grid of ``planar_ncc_scale`` of the image size with
    ``planar_ncc_window``² ZNCC windows against up to ``planar_ncc_views`` other views
    chosen per view for how many of its candidate plane points they see
    (:func:`coverage_views`), each sampled at the plane point's projection.
    A pixel is accepted when ≥ ``planar_min_views`` of them (or all there are) see the point
    unoccluded and whole windows inside their image (an occluded one: its depth there is
    < (1 − 3 %) of the point's depth in it), the mean ZNCC over those is
    ≥ ``planar_min_ncc`` and exceeds the mean ZNCC at depths × (1 ± ``planar_offset_rel``)
    by ≥ ``planar_ncc_margin``, the reference window has texture (std ≥ 1 grey level), and
    no own SGBM depth nearer than the plane by > 5 % lies within ``planar_ncc_window``
    pixels. A pixel whose nearest plane is rejected tries the planes behind it in turn.
    A far SGBM depth that disagrees with an accepted plane depth by more than
    ``far_consistency_rel_tol`` is replaced; one that agrees is kept, the plane depth its
    ``fallback``. Raises ShapeError on mismatched inputs.
    """
    _check_views(views, depths)
    n = len(views)
    stats: dict[str, Any] = {
        "planes": [p.to_json() for p in planes],
        "pixels_filled": 0,
        "far_pixels_replaced": 0,
    }
    if not planes:
        fills = [_ViewFill.unchanged(d, ()) for d in depths]
    else:
        scaled = _scaled_views(views, depths, options.planar_ncc_scale)
        fills = []
        for i in range(n):
            fills.append(_fill_view(i, views, depths[i], planes, scaled, options))
            progress("planar", (i + 1) / n)
    for f in fills:
        stats["pixels_filled"] += f.filled
        stats["far_pixels_replaced"] += f.replaced
    return PlaneFill(
        [f.depth for f in fills],
        [f.from_plane for f in fills],
        [f.fallback for f in fills],
        [f.checked_by for f in fills],
        stats,
    )


def _fill_view(
    i: int,
    views: list[DenseView],
    depth: F32,
    planes: list[Plane],
    scaled: _ScaledViews,
    options: ReconstructOptions,
) -> _ViewFill:
    """View ``i``'s (H, W) ``depth`` with its verified plane depths laid in (see
    :func:`fill_depths`). A pixel whose nearest plane the photos reject (or which is nearer
    than ``planar_min_depth_m``) tries the next plane behind it, so a spurious plane (one
    through the tops of objects) cannot hide the floor and walls; one round per plane at
    most, each with verifying views chosen for its own candidates."""
    hs, ws = scaled.grays[i].shape
    label_acc = np.full((hs, ws), -1, np.int16)
    beyond = np.zeros((hs, ws), np.float32)
    checked_by: list[int] = []
    for _ in planes:
        cands = _candidates(i, views[i], planes, scaled, options, beyond)
        chosen = _choose_views(cands, views, scaled, options) if cands.mask.any() else ()
        accept_s = (
            _accepted(cands, views, scaled, chosen, options)
            if chosen
            else np.zeros((hs, ws), np.bool_)
        )
        label_acc[accept_s] = cands.label[accept_s]
        checked_by += [j for j in chosen if j not in checked_by]
        # occluders' pixels (own depth near) stay too: the edge test of their neighbours
        # compares the own depth with the plane depth behind it
        retry = (cands.depth > 0) & ~accept_s
        if not retry.any():
            break
        beyond = np.where(retry, cands.depth * np.float32(1.0 + 1e-4), np.inf).astype(np.float32)
    if not (label_acc >= 0).any():
        return _ViewFill.unchanged(depth, tuple(checked_by))
    return _lay_in(views[i], depth, planes, label_acc, tuple(checked_by), options)


def _accepted(
    cands: _Candidates,
    views: list[DenseView],
    scaled: _ScaledViews,
    checked_by: tuple[int, ...],
    options: ReconstructOptions,
) -> NDArray[np.bool_]:
    """(h, w) bool: the candidate pixels whose plane depth the views ``checked_by`` verify
    photometrically (the acceptance rule of :func:`fill_depths`)."""
    win = options.planar_ncc_window
    plane_s = cands.depth
    own_s = scaled.depths[cands.index]
    # a nearer SGBM depth close by: an occluder's edge, where the plane would bleed
    nearer = (own_s > 0) & (own_s < options.far_min_depth_m) & (own_s < 0.95 * plane_s)
    nearer = cv2.dilate(nearer.astype(np.uint8), np.ones((win, win), np.uint8)) > 0
    g_ref = scaled.grays[cands.index]
    ref = WindowStats.of(g_ref, win)
    textured = ref.var >= 1.0
    hs, ws = g_ref.shape
    rays = _rays_cam(scaled.k_matrices[cands.index], ws, hs)
    scores = np.zeros((3, hs, ws), np.float32)
    used = np.zeros((hs, ws), np.int32)
    for j in checked_by:
        pair = _pair_scores(cands, views, j, ref, rays, scaled, options)
        used += pair.valid
        scores += pair.ncc
    need = min(options.planar_min_views, len(checked_by))
    with np.errstate(divide="ignore", invalid="ignore"):
        mean_scores = scores / np.maximum(used, 1)
    accept_s = (
        (used >= need)
        & textured
        & ~nearer
        & (mean_scores[0] >= options.planar_min_ncc)
        & (mean_scores[0] >= np.maximum(mean_scores[1], mean_scores[2]) + options.planar_ncc_margin)
    )
    return np.asarray(accept_s & cands.mask)


@dataclass(frozen=True)
class _PairScores:
    """One verifying view's (3, h, w) float32 ZNCC at the plane depth and at depths
    × (1 ∓ ``planar_offset_rel``) (0 where it does not count), and (h, w) bool where it
    counts (sees the plane point unoccluded, whole window inside its image)."""

    ncc: F32
    valid: NDArray[np.bool_]


def _pair_scores(
    cands: _Candidates,
    views: list[DenseView],
    j: int,
    ref: WindowStats,
    rays: NDArray[np.float32],
    scaled: _ScaledViews,
    options: ReconstructOptions,
) -> _PairScores:
    """ZNCC of view ``cands.index``'s reference windows against view j, sampled through the
    candidate plane points and through the points ± ``planar_offset_rel`` along the ray."""
    win = options.planar_ncc_window
    eps = options.planar_offset_rel
    plane_s = cands.depth
    hs, ws = plane_s.shape
    # the point at depth z on the ray r of view i is a + z M r in view j's camera
    j_from_i = views[j].cam_from_env @ views[cands.index].env_from_cam
    a = j_from_i[:3, 3]
    m_rays = [_linear(rays, row) for row in j_from_i[:3, :3]]
    kj = scaled.k_matrices[j]
    hj, wj = scaled.grays[j].shape
    kernel = np.ones((win, win), np.uint8)
    valid_j = np.zeros((hs, ws), np.bool_)
    ncc_all = np.zeros((3, hs, ws), np.float32)
    for k, factor in enumerate((1.0, 1.0 - eps, 1.0 + eps)):
        zf = plane_s * np.float32(factor)
        qx, qy, qz = (np.float32(a[c]) + zf * m_rays[c] for c in range(3))
        with np.errstate(divide="ignore", invalid="ignore"):
            mx = np.float32(kj[0, 0]) * qx / qz + np.float32(kj[0, 2])
            my = np.float32(kj[1, 1]) * qy / qz + np.float32(kj[1, 2])
        inside = (qz > 0) & (mx >= 0) & (mx <= wj - 1) & (my >= 0) & (my <= hj - 1)
        mx[~inside] = -1.0
        my[~inside] = -1.0
        if k == 0:
            seen = cv2.remap(scaled.depths[j], mx, my, cv2.INTER_NEAREST, borderValue=0.0)
            occluded = (seen > 0) & (seen < 0.97 * qz)
            full = cv2.erode(inside.astype(np.uint8), kernel) > 0
            valid_j = full & ~occluded & (plane_s > 0)
        warped = np.asarray(
            cv2.remap(scaled.grays[j], mx, my, cv2.INTER_LINEAR, borderValue=0.0), np.float32
        )
        ncc_all[k] = np.where(valid_j, zncc(ref, warped, win), 0.0).astype(np.float32)
    return _PairScores(ncc_all, valid_j)


def _lay_in(
    view: DenseView,
    depth: F32,
    planes: list[Plane],
    label_acc: NDArray[np.int16],
    checked_by: tuple[int, ...],
    options: ReconstructOptions,
) -> _ViewFill:
    """The view's (H, W) ``depth`` with the plane depths of the accepted (h, w) plane labels
    ``label_acc`` (−1: none) laid in at full resolution: into pixels with no depth, and over
    far depths that disagree by more than ``far_consistency_rel_tol``; far depths that
    agree are kept, the plane depth their fallback."""
    w, h = view.size
    label = np.asarray(cv2.resize(label_acc, (w, h), interpolation=cv2.INTER_NEAREST), np.int16)
    plane_full = _label_depths(view, planes, label)
    accept = (plane_full >= max(options.planar_min_depth_m, 1e-6)) & (
        (depth <= 0) | (depth >= options.far_min_depth_m)
    )
    empty = accept & (depth <= 0)
    far = accept & (depth > 0)
    agree = far & (np.abs(depth - plane_full) <= options.far_consistency_rel_tol * plane_full)
    replace = far & ~agree
    new = depth.copy()
    new[empty | replace] = plane_full[empty | replace]
    fallback = np.where(agree, plane_full, 0.0).astype(np.float32)
    filled, replaced = int(empty.sum()), int(replace.sum())
    return _ViewFill(
        new.astype(np.float32), empty | replace, fallback, checked_by, filled, replaced
    )
