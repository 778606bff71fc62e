"""An object's turn on its support and shift across it from the photos' edges.

Stereo blurs a low object's sides into its support and bleeds its outline outward, unevenly
where the light, the lens or the blur differ between views, so the outline of the scan
(:mod:`~workers.pipeline.pose.top_view`) can hold a turn of a few degrees that is not the
object's; a tall object's cloud holds its turn about the vertical only by the few features
that break its near-symmetry. The photos keep its silhouette sharp: :func:`fit_photo_edges`
turns the pose about the support's normal and shifts it across the support so that the
posed model's silhouette in each photo lies on the photo's edges. All points are (N, 3)
float64 metres; poses are 4×4 ``env_from_object``; distances on images are in image pixels.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from workers.pipeline.compare.data import Camera, CaptureData
from workers.pipeline.compare.files import read_photo
from workers.pipeline.compare.visibility import (
    DepthMap,
    camera_coords,
    depth_at,
    project_in_image,
)
from workers.pipeline.geometry import Mat4, Points
from workers.pipeline.pose.top_view import least_turn_and_shift, turned_in_plane

#: Canny's hysteresis thresholds on the 8-bit grey photo blurred over 3×3 pixels
CANNY_LOW, CANNY_HIGH = 30, 90
#: least share of the posed silhouette a photo must show for it to count: an occluder's
#: edge is not the object's
MIN_SHOWN = 0.9
#: a silhouette point is hidden where the capture's depth lies this much nearer than the
#: model's nearest point (something stands in front of it), metres
OCCLUDER_GAP_M = 0.01
#: least silhouette length in a photo, pixels
MIN_RIM_PX = 40
#: turns about the support's normal each fit starts from, degrees
START_TURNS_DEG = (0.0, -3.0, 3.0)
#: the fit is repeated around its result (the silhouette chosen again) this many times
PASSES = 2


class EdgeModel(Protocol):
    """What the fit needs of a model (a :class:`~workers.pipeline.model.PreparedModel` is
    one): (N, 3) surface samples, their (N, 3) unit outward normals and (3,) centre, object
    frame, metres."""

    @property
    def points(self) -> Points: ...

    @property
    def normals(self) -> Points: ...

    @property
    def centre_object(self) -> NDArray[np.float64]: ...


@dataclass
class CaptureSight:
    """A capture as the pose step looks at it: its data, its ``depth_maps`` (None: none
    rendered) and its photos' edges, read on first use and kept."""

    capture: CaptureData
    depth_maps: Sequence[DepthMap] | None
    _distance: dict[str, NDArray[np.float32] | None] = field(
        default_factory=dict, init=False, repr=False
    )

    def edge_distance(self, camera: Camera) -> NDArray[np.float32] | None:
        """(H, W) float32 distance in pixels from each pixel of ``camera``'s photo
        (undistorted) to its nearest edge; None: no photo, or it could not be read."""
        if camera.name not in self._distance:
            self._distance[camera.name] = _edge_distance(self.capture, camera)
        return self._distance[camera.name]


def _edge_distance(capture: CaptureData, camera: Camera) -> NDArray[np.float32] | None:
    import cv2  # heavy: imported only when a photo is read

    path = capture.photos.get(camera.name)
    if path is None:
        return None
    rgb = read_photo(path, camera, max(camera.width, camera.height))
    if rgb is None or rgb.shape[:2] != (camera.height, camera.width):
        return None
    grey = cv2.cvtColor(np.asarray(rgb * 255.0, dtype=np.uint8), cv2.COLOR_RGB2GRAY)
    edges = cv2.Canny(cv2.GaussianBlur(grey, (3, 3), 0), CANNY_LOW, CANNY_HIGH)
    distance = cv2.distanceTransform((edges == 0).astype(np.uint8), cv2.DIST_L2, 3)
    return np.asarray(distance, dtype=np.float32)


@dataclass(frozen=True)
class _Rim:
    """The model points (object frame, (K, 3)) on the posed silhouette in one photo."""

    camera: Camera
    distance: NDArray[np.float32]
    points_object: Points


def _silhouette(uv: NDArray[np.float64]) -> NDArray[np.float64]:
    """(P, 2) pixels of the outer contour of the (N, 2) projected points, closed over gaps
    of a few pixels."""
    import cv2

    lo = np.floor(uv.min(axis=0)).astype(int) - 4
    hi = np.ceil(uv.max(axis=0)).astype(int) + 4
    mask = np.zeros((hi[1] - lo[1] + 1, hi[0] - lo[0] + 1), dtype=np.uint8)
    ij = np.round(uv - lo).astype(int)
    mask[ij[:, 1], ij[:, 0]] = 255
    mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, np.ones((5, 5), dtype=np.uint8))
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return np.zeros((0, 2))
    out: NDArray[np.float64] = np.vstack([c[:, 0, :] for c in contours]).astype(np.float64) + lo
    return out


def _rims(
    model: EdgeModel, env_from_object: Mat4, sight: CaptureSight, max_views: int
) -> list[_Rim]:
    """The silhouettes of the posed model in the photos that show all of it: in the image,
    and at least :data:`MIN_SHOWN` of the silhouette not behind something nearer than the
    model's nearest point by :data:`OCCLUDER_GAP_M`; at most ``max_views`` of them (the
    longest)."""
    posed = model.points @ env_from_object[:3, :3].T + env_from_object[:3, 3]
    found: list[tuple[int, _Rim]] = []
    for dm in sight.depth_maps or ():
        uv, z, inside = project_in_image(dm.camera, posed)
        if not inside.all():
            continue
        contour = _silhouette(uv)
        if len(contour) < MIN_RIM_PX:
            continue
        _, nearest = cKDTree(uv).query(contour)
        rim = np.unique(nearest)
        if np.mean(depth_at(dm, uv[rim]) < z.min() - OCCLUDER_GAP_M) > 1.0 - MIN_SHOWN:
            continue
        distance = sight.edge_distance(dm.camera)
        if distance is None:
            continue
        found.append((len(contour), _Rim(dm.camera, distance, model.points[rim])))
    found.sort(key=lambda item: -item[0])
    return [rim for _, rim in found[:max_views]]


@dataclass(frozen=True)
class _RimStack:
    """The chosen silhouettes stacked for :func:`_cost`: (K, 3) object-frame points, each
    point's photo (K,), its camera (``k`` (3, 3, K), ``cam_from_env`` (3, 4, K), image
    ``width``/``height`` (K,)), offset into the photos' distance maps laid end to end
    (flat float32) and ``per_view``, the (views,) count of points per photo."""

    points_object: Points
    view: NDArray[np.int64]
    k: NDArray[np.float64]
    cam_from_env: NDArray[np.float64]
    width: NDArray[np.int64]
    height: NDArray[np.int64]
    offset: NDArray[np.int64]
    distance: NDArray[np.float32]
    per_view: NDArray[np.int64]


def _stack(rims: Sequence[_Rim]) -> _RimStack:
    """(≥ 1) silhouettes stacked."""
    view = np.repeat(np.arange(len(rims)), [len(r.points_object) for r in rims])

    def per_point(values: list[NDArray[Any]]) -> NDArray[Any]:
        return np.ascontiguousarray(np.moveaxis(np.stack(values)[view], 0, -1))

    area = np.array([r.distance.size for r in rims])
    return _RimStack(
        points_object=np.vstack([r.points_object for r in rims]),
        view=view,
        k=per_point([r.camera.k for r in rims]),
        cam_from_env=per_point([r.camera.cam_from_env[:3, :4] for r in rims]),
        width=np.array([r.camera.width for r in rims])[view],
        height=np.array([r.camera.height for r in rims])[view],
        offset=(np.cumsum(area) - area)[view],
        distance=np.concatenate([r.distance.ravel() for r in rims]),
        per_view=np.bincount(view, None, len(rims)),
    )


def _cost(stack: _RimStack, env_from_object: Mat4, cap_px: float) -> float:
    """Mean over the photos of the mean distance (pixels, capped at ``cap_px``) from the
    projected silhouette points to the photo's nearest edge. Called ~10⁴ times a pose: the
    projection is :func:`~workers.pipeline.compare.visibility.project_points`' arithmetic
    without its masked copies (a point out of the image reads a clipped pixel, then
    ``cap_px``)."""
    posed = stack.points_object @ env_from_object[:3, :3].T + env_from_object[:3, 3]
    xc, yc, zc = camera_coords(stack.cam_from_env, posed[:, 0], posed[:, 1], posed[:, 2])
    k = stack.k
    front = zc > 1e-6
    zs = np.where(front, zc, 1.0)
    xn, yn = xc / zs, yc / zs
    u = k[0, 0] * xn + k[0, 1] * yn + k[0, 2]
    v = k[1, 1] * yn + k[1, 2]
    width, height = stack.width, stack.height
    inside = front & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    col = np.clip(np.round(u).astype(int), 0, width - 1)
    row = np.clip(np.round(v).astype(int), 0, height - 1)
    at = np.minimum(stack.distance[stack.offset + row * width + col], cap_px)
    d = np.where(inside, at, cap_px)
    per_view = np.bincount(stack.view, d, len(stack.per_view)) / stack.per_view
    return float(per_view.mean())


def _fit_pass(
    rims: Sequence[_Rim],
    pose: Mat4,
    centre_object: NDArray[np.float64],
    normal_env: NDArray[np.float64],
    cap_px: float,
    starts_deg: Sequence[float],
) -> Mat4:
    """One pass of :func:`fit_photo_edges` on chosen silhouettes: the least-cost pose from
    ``pose`` turned by each of ``starts_deg``."""
    centre = pose[:3, :3] @ centre_object + pose[:3, 3]
    stack = _stack(rims)

    def cost(x: NDArray[np.float64]) -> float:
        return _cost(stack, turned_in_plane(pose, normal_env, centre, x), cap_px)

    best_x = least_turn_and_shift(cost, starts_deg, ftol=1e-5)
    return turned_in_plane(pose, normal_env, centre, best_x)


@dataclass(frozen=True)
class EdgeFit:
    """The pose the photos' edges hold (``env_from_object``), its ``cost`` (mean pixels to
    the nearest edge) and the start's, each on its own silhouettes, and ``views``, the
    photos that took part (0: no fit, the start returned)."""

    env_from_object: Mat4
    cost: float
    start_cost: float
    views: int


def fit_photo_edges(
    model: EdgeModel,
    start: Mat4,
    normal_env: NDArray[np.float64],
    sight: CaptureSight,
    cap_px: float,
    max_views: int,
    starts_deg: Sequence[float] = START_TURNS_DEG,
) -> EdgeFit:
    """``start`` turned about the unit ``normal_env`` (the support's) through the object's
    centre and shifted across the plane so that the model's silhouette lies on the edges
    of the photos of ``sight`` that show all of it: mean distances capped at ``cap_px``
    over at most ``max_views`` photos, minimised (Powell) from ``start`` turned by each of
    ``starts_deg``, the silhouettes chosen again around the result (:data:`PASSES`). No
    photo shows it: ``start``, ``views`` 0."""
    pose = start
    rims = _rims(model, pose, sight, max_views)
    if not rims:
        return EdgeFit(start, float("inf"), float("inf"), 0)
    start_cost = _cost(_stack(rims), start, cap_px)
    for i in range(PASSES):
        turns = starts_deg if i == 0 else (0.0,)
        pose = _fit_pass(rims, pose, model.centre_object, normal_env, cap_px, turns)
        rims = _rims(model, pose, sight, max_views) or rims
    return EdgeFit(pose, _cost(_stack(rims), pose, cap_px), start_cost, len(rims))
