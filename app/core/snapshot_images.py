"""A snapshot's photos as the console shows them: each with its size, its camera (when the
reconstruction registered it) and the detector's boxes in pixels; and one photo's bytes."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import PurePosixPath
from typing import Any

import numpy as np
from numpy.typing import NDArray
from sqlalchemy import select
from sqlalchemy.orm import Session

from app.core.errors import Conflict, Gone, NotFound
from app.core.models import Snapshot, SnapshotImage
from app.core.storage import Storage
from app.formats import FormatError
from app.formats.cameras import (
    CamerasFile,
    from_reconstruction_images,
    is_reconstruction_images,
    read_cameras,
)

MEDIA_TYPES = {".jpg": "image/jpeg", ".jpeg": "image/jpeg", ".png": "image/png"}


@dataclass(frozen=True)
class PinholeCamera:
    """A registered photo's camera: ``k`` (3, 3) pixels (the pinhole part of its params;
    distortion left out, as every stage takes the images as undistorted), its image size in
    pixels and ``env_from_cam`` (4, 4) metres, OpenCV axes (x right, y down, z forward)."""

    name: str
    k: NDArray[np.float64]
    width: int
    height: int
    env_from_cam: NDArray[np.float64]

    @property
    def cam_from_env(self) -> NDArray[np.float64]:
        return np.asarray(np.linalg.inv(self.env_from_cam), dtype=np.float64)


@dataclass(frozen=True)
class Detection:
    """One detector box: ``box_px`` ``[x0, y0, x1, y1]`` pixels of the photo."""

    class_name: str
    class_id: int
    box_px: tuple[float, float, float, float]
    confidence: float | None


@dataclass(frozen=True)
class PhotoInfo:
    name: str
    width: int
    height: int
    camera: PinholeCamera | None
    detections: list[Detection]


def cameras_of(storage: Storage, snap: Snapshot) -> dict[str, PinholeCamera]:
    """The reconstruction's registered cameras by image name (none before it is
    reconstructed). Conflict (409 CamerasUnreadable) when its cameras.json cannot be read."""
    if not snap.cameras_key:
        return {}
    try:
        doc: Any = json.loads(storage.local_file(snap.cameras_key).read_text(encoding="utf-8-sig"))
        parsed: CamerasFile = (
            from_reconstruction_images(doc) if is_reconstruction_images(doc) else read_cameras(doc)
        )
    except (OSError, ValueError, FormatError) as exc:
        raise Conflict(
            f"snapshot {snap.id}: its cameras.json cannot be read ({exc})",
            code="CamerasUnreadable",
        ) from exc
    out: dict[str, PinholeCamera] = {}
    for name, pose in parsed.poses.items():
        camera = parsed.camera_for(name)
        if camera is None:
            continue
        fx, fy, cx, cy = camera.pinhole
        out[name] = PinholeCamera(
            name=name,
            k=np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]),
            width=camera.width,
            height=camera.height,
            env_from_cam=np.asarray(pose, dtype=np.float64),
        )
    return out


def detections_px(image: SnapshotImage) -> list[Detection]:
    """The image's YOLO detections (normalised centre and size) as pixel boxes."""
    out = []
    for d in image.detections:
        cx, cy = float(d["cx"]) * image.width, float(d["cy"]) * image.height
        hw, hh = float(d["w"]) * image.width / 2, float(d["h"]) * image.height / 2
        conf = d.get("confidence")
        out.append(
            Detection(
                class_name=str(d.get("class") or d["class_id"]),
                class_id=int(d["class_id"]),
                box_px=(cx - hw, cy - hh, cx + hw, cy + hh),
                confidence=None if conf is None else float(conf),
            )
        )
    return out


def image_rows(session: Session, snapshot_id: str) -> list[SnapshotImage]:
    """The snapshot's image rows by name."""
    return list(
        session.scalars(
            select(SnapshotImage)
            .where(SnapshotImage.snapshot_id == snapshot_id)
            .order_by(SnapshotImage.name)
        ).all()
    )


def photos(session: Session, storage: Storage, snap: Snapshot) -> list[PhotoInfo]:
    """Every photo of the snapshot by name, with its camera and detections."""
    cameras = cameras_of(storage, snap)
    return [
        PhotoInfo(
            name=row.name,
            width=row.width,
            height=row.height,
            camera=cameras.get(row.name),
            detections=detections_px(row),
        )
        for row in image_rows(session, snap.id)
    ]


def photo_file(session: Session, storage: Storage, snap: Snapshot, name: str) -> tuple[str, str]:
    """The storage key and media type of photo ``name``: 404 when the snapshot has no photo
    of that name, 410 ImagesDeleted when retention (or a deletion) removed the photos."""
    row = session.scalar(
        select(SnapshotImage).where(
            SnapshotImage.snapshot_id == snap.id, SnapshotImage.name == name
        )
    )
    if row is None:
        raise NotFound(f"snapshot {snap.id} has no image {name!r}")
    if snap.images_deleted_at is not None or not storage.exists(row.file_key):
        when = snap.images_deleted_at.isoformat() if snap.images_deleted_at else "earlier"
        raise Gone(
            f"the photos of snapshot {snap.id} were deleted ({when}) by the retention policy; "
            "its cloud, cameras and detections are kept",
            code="ImagesDeleted",
        )
    media = MEDIA_TYPES.get(PurePosixPath(row.file_key).suffix.lower(), "application/octet-stream")
    return row.file_key, media
