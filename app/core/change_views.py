"""What the console shows of a comparison's changes: the change clusters' points
(:mod:`app.core.change_clusters`) and, per photo that saw a change's cluster, its re-projected
outline beside the detector's box that identified it.

The identify stage keeps, per cluster and photo, the cluster's box (the comparison's
``clusters`` table, ``boxes``); the outline is computed here the way that stage saw the
cluster: the stored cluster points projected into the photo's camera, kept where visible
(in front, inside the image, and no deeper than the capture's own surface there plus a
tolerance: a z-buffer of the snapshot's cloud, decimated to ``zbuffer_max_points``, at
``zbuffer_max_side`` px, eroded by ``zbuffer_fill_px``; the comparison's own options), and
their convex hull. The detection is the photo's best-overlapping box of the change's class
(IoU with the cluster's box, as the identify stage scores it); ``counted``: the photo added
to that class's overlaps (IoU > 0).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from sqlalchemy import select
from sqlalchemy.orm import Session

from app.core import change_clusters, snapshot_images, snapshots
from app.core.change_clusters import StoredCluster
from app.core.enums import ComparisonState
from app.core.errors import Conflict, NotFound
from app.core.export import decimate
from app.core.export.ply import PlyError, read_header
from app.core.models import Change, Comparison, Environment, Job, Snapshot
from app.core.snapshot_images import PinholeCamera
from app.core.storage import Storage

FloatArray = NDArray[np.float64]
# The compare stage's defaults (workers.pipeline.compare.options), used when a comparison's
# resolved options do not name them.
DEFAULTS: dict[str, float] = {
    "zbuffer_max_side": 256,
    "zbuffer_max_points": 400_000,
    "zbuffer_fill_px": 1,
    "depth_tolerance_m": 0.02,
    "depth_tolerance_px": 2.0,
}


@dataclass(frozen=True)
class View:
    """One photo that saw a change's cluster. Pixels of the photo; ``outline_px`` (n, 2)
    the convex hull of the visible projected points, counter-clockwise (empty when none
    is visible from the stored points)."""

    image: str
    outline_px: list[list[float]]
    box_px: list[float]
    detection_box_px: list[float] | None
    iou: float | None
    counted: bool


def stored_clusters(
    session: Session, storage: Storage, comparison: Comparison
) -> list[StoredCluster]:
    """The comparison's cluster points. Conflict (409) ComparisonNotSucceeded before it
    succeeded; ClustersNotStored for one made before the service kept them (re-run it)."""
    if comparison.state != ComparisonState.succeeded:
        raise Conflict(
            f"comparison {comparison.id} is {comparison.state}: its clusters exist once it "
            "succeeded",
            code="ComparisonNotSucceeded",
        )
    after = snapshots.get(session, comparison.after_id)
    job = session.get(Job, comparison.job_id)
    found = None
    if job is not None:  # the attempt that succeeded published them
        key = change_clusters.clusters_key(
            after.storage_prefix, comparison.id, job.id, job.attempts
        )
        found = change_clusters.read(storage, key)
    if found is None:  # made before attempts had folders
        found = change_clusters.read(
            storage, change_clusters.clusters_key(after.storage_prefix, comparison.id)
        )
    if found is None:
        raise Conflict(
            f"comparison {comparison.id} was made before cluster points were kept; run it "
            "again (POST /v1/environments/{id}/comparisons) to get them",
            code="ClustersNotStored",
        )
    return found


def change_of(session: Session, comparison: Comparison, change_id: str) -> Change:
    """The comparison's change ``change_id``; 404 when it has none of that id."""
    change = session.scalar(
        select(Change).where(Change.comparison_id == comparison.id, Change.id == change_id)
    )
    if change is None:
        raise NotFound(f"comparison {comparison.id} has no change {change_id}")
    return change


def views(session: Session, storage: Storage, comparison: Comparison, change_id: str) -> list[View]:
    """Every photo of the change's cluster's capture that saw the cluster, by name (module
    docstring). 404 for an unknown change; 409 as :func:`stored_clusters`."""
    change = change_of(session, comparison, change_id)
    cluster_json: Mapping[str, Any] = change.cluster or {}
    cluster_id, side = cluster_json.get("id"), cluster_json.get("side")
    stored = {c.id: c for c in stored_clusters(session, storage, comparison)}
    row = next((r for r in comparison.clusters if r.get("id") == cluster_id), None)
    if cluster_id not in stored or row is None:
        raise Conflict(
            f"change {change_id}'s cluster {cluster_id} is not among the comparison's "
            "stored clusters",
            code="ClustersNotStored",
        )
    snap = snapshots.get(session, comparison.after_id if side == "added" else comparison.before_id)
    if not snap.pointcloud_key:
        raise Conflict(f"snapshot {snap.id} has no point cloud", code="PointCloudNotReady")
    options = {**DEFAULTS, **(comparison.options or {}).get("resolved", {})}
    cameras = snapshot_images.cameras_of(storage, snap)
    rows = {r.name: r for r in snapshot_images.image_rows(session, snap.id)}
    env = session.get_one(Environment, comparison.environment_id)
    identified = (change.identification or {}).get("object") or change.object_name
    class_id = env.classes.index(identified) if identified in env.classes else None
    cloud = _cloud_columns(storage, snap, int(options["zbuffer_max_points"]))
    points = np.asarray(stored[cluster_id].points_env, dtype=np.float64)
    out: list[View] = []
    for name, box in sorted((row.get("boxes") or {}).items()):
        camera = cameras.get(name)
        if camera is None:
            continue
        depth, scale = depth_buffer(
            camera, cloud, int(options["zbuffer_max_side"]), int(options["zbuffer_fill_px"])
        )
        uv, visible = visible_pixels(
            camera,
            points,
            depth,
            scale,
            float(options["depth_tolerance_m"]),
            float(options["depth_tolerance_px"]),
        )
        det_box, iou = None, None
        image = rows.get(name)
        if class_id is not None and image is not None:
            det_box, iou = best_detection(box, image, class_id)
        out.append(
            View(
                image=name,
                outline_px=[[round(float(u), 1), round(float(v), 1)] for u, v in hull(uv[visible])],
                box_px=[float(v) for v in box],
                detection_box_px=det_box,
                iou=iou,
                counted=bool(iou is not None and iou > 0),
            )
        )
    return out


def best_detection(
    box_px: list[float], image: Any, class_id: int
) -> tuple[list[float] | None, float | None]:
    """The image's detection of ``class_id`` with the highest IoU with ``box_px`` and that
    IoU; (None, 0.0) when it has none of the class (the photo counted no overlap)."""
    best: tuple[list[float] | None, float] = (None, 0.0)
    for det in snapshot_images.detections_px(image):
        if det.class_id != class_id:
            continue
        iou = box_iou(box_px, det.box_px)
        if best[0] is None or iou > best[1]:
            best = ([float(v) for v in det.box_px], iou)
    return best


def box_iou(a: Any, b: Any) -> float:
    """IoU of two boxes ``[x0, y0, x1, y1]``; 0 when either is empty."""
    w = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    h = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = w * h
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return float(inter / union) if union > 0 else 0.0


def _cloud_columns(storage: Storage, snap: Snapshot, max_points: int) -> NDArray[np.float32]:
    """(3, N) float32 columns of the snapshot's cloud, decimated to ``max_points`` (the
    cached file of :mod:`app.core.export.decimate`)."""
    assert snap.pointcloud_key is not None
    cached = decimate.ensure_decimated(storage, snap.pointcloud_key, max_points)
    path = storage.local_file(cached.key)
    try:
        header, vertex = read_header(path)
    except PlyError as exc:
        raise Conflict(str(exc), code="PointCloudUnreadable") from exc
    records = np.fromfile(
        path, dtype=decimate.RECORD, count=vertex.count, offset=header.header_bytes
    )
    return np.stack([records["x"], records["y"], records["z"]]).astype(np.float32)


def _camera_coords(
    cam_from_env: FloatArray, cols: NDArray[Any]
) -> tuple[NDArray[Any], NDArray[Any], NDArray[Any]]:
    m = cam_from_env.astype(cols.dtype)
    x, y, z = cols[0], cols[1], cols[2]
    return (
        x * m[0, 0] + y * m[0, 1] + z * m[0, 2] + m[0, 3],
        x * m[1, 0] + y * m[1, 1] + z * m[1, 2] + m[1, 3],
        x * m[2, 0] + y * m[2, 1] + z * m[2, 2] + m[2, 3],
    )


def depth_buffer(
    camera: PinholeCamera, cloud_cols: NDArray[np.float32], max_side: int, fill_px: int
) -> tuple[NDArray[np.float32], float]:
    """Z-buffer (h, w) float32 metres along the camera's z (inf where nothing projects) of
    (3, N) environment points, at ``scale`` buffer pixels per image pixel (the longer side
    ≤ ``max_side``), eroded by a (2·fill_px + 1)² minimum; and ``scale``."""
    scale = min(1.0, max_side / max(camera.width, camera.height))
    w, h = max(1, round(camera.width * scale)), max(1, round(camera.height * scale))
    xc, yc, zc = _camera_coords(camera.cam_from_env, cloud_cols)
    front = zc > 1e-6
    xc, yc, zc = xc[front], yc[front], zc[front]
    k = camera.k
    u = (k[0, 0] * xc / zc + k[0, 1] * yc / zc + k[0, 2]) * (w / camera.width)
    v = (k[1, 1] * yc / zc + k[1, 2]) * (h / camera.height)
    ok = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    lin = v[ok].astype(np.int64) * w + u[ok].astype(np.int64)
    buf = np.full(w * h, np.inf, dtype=np.float32)
    np.minimum.at(buf, lin, zc[ok].astype(np.float32))
    depth = buf.reshape(h, w)
    for _ in range(max(0, fill_px)):
        padded = np.pad(depth, 1, mode="edge")
        depth = np.minimum.reduce(
            [padded[dy : dy + h, dx : dx + w] for dy in range(3) for dx in range(3)]
        )
    return depth, scale


def visible_pixels(
    camera: PinholeCamera,
    points_env: FloatArray,
    depth: NDArray[np.float32],
    scale: float,
    tol_m: float,
    tol_px: float,
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Pixels (N, 2) of the photo and which of (N, 3) points are visible in it: in front,
    inside the image, and at most ``tol_m + tol_px · z / f`` behind the z-buffer (f the
    smaller focal length in buffer pixels)."""
    cols = np.asarray(points_env, dtype=np.float64).T
    xc, yc, z = _camera_coords(camera.cam_from_env, cols)
    k = camera.k
    with np.errstate(divide="ignore", invalid="ignore"):
        zs = np.where(z > 1e-6, z, np.nan)
        uv = np.column_stack(
            [k[0, 0] * xc / zs + k[0, 1] * yc / zs + k[0, 2], k[1, 1] * yc / zs + k[1, 2]]
        )
        inside = (
            (z > 1e-6)
            & (uv[:, 0] >= 0)
            & (uv[:, 0] < camera.width)
            & (uv[:, 1] >= 0)
            & (uv[:, 1] < camera.height)
        )
    h, w = depth.shape
    zbuf = np.full(len(z), np.inf)
    col = np.clip((uv[inside, 0] * scale).astype(np.int64), 0, w - 1)
    row = np.clip((uv[inside, 1] * scale).astype(np.int64), 0, h - 1)
    zbuf[inside] = depth[row, col]
    focal = float(min(k[0, 0], k[1, 1]) * scale)
    with np.errstate(invalid="ignore"):
        visible = inside & (z <= zbuf + tol_m + tol_px * np.abs(z) / focal)
    return uv, visible


def hull(points_px: FloatArray) -> FloatArray:
    """Convex hull (h, 2) of (n, 2) pixels in order around it, without repeating the first
    point (Andrew's monotone chain over the points rounded to whole pixels); all of them
    when fewer than 3 distinct."""
    pts = np.unique(np.round(np.asarray(points_px, dtype=np.float64)), axis=0)
    if len(pts) < 3:
        return np.asarray(pts, dtype=np.float64)

    def cross(o: FloatArray, a: FloatArray, b: FloatArray) -> float:
        return float((a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]))

    lower: list[FloatArray] = []
    for p in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= 0:
            lower.pop()
        lower.append(p)
    upper: list[FloatArray] = []
    for p in pts[::-1]:
        while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= 0:
            upper.pop()
        upper.append(p)
    return np.array(lower[:-1] + upper[:-1], dtype=np.float64)
