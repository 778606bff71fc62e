"""The worker's ingest stage: re-read a stored capture with the upload's parsers and record
one SnapshotImage row per image."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.core import snapshots
from app.core.ingest.common import IMAGE_SUFFIXES
from app.core.ingest.images import probe_image
from app.core.ingest.parsers import parse_detections
from app.core.models import SnapshotImage, utcnow
from app.core.settings import Settings
from app.core.storage import Storage


@dataclass(frozen=True)
class ImageRecord:
    """What the worker's ingest stage records for one stored image."""

    name: str
    file_key: str
    width: int
    height: int
    size_bytes: int
    labels_key: str | None
    detections: list[dict[str, Any]]


# --- the worker's ingest stage --------------------------------------------------------------


def read_capture(
    storage: Storage,
    prefix: str,
    classes: Sequence[str],
    settings: Settings,
    images_dir: Path | None = None,
) -> list[ImageRecord]:
    """Re-read a stored capture: each image's size (checked as on upload) and its detections,
    sorted by image name. ``images_dir``: the photos' local folder when the caller fetched
    it already (``storage.local_dir(f"{prefix}/images")``; with S3 each fetch lists the
    bucket). Raises the upload's DomainErrors if the files changed since."""
    if images_dir is None:
        images_dir = storage.local_dir(f"{prefix}/images")
    try:
        labels_dir: Path | None = storage.local_dir(f"{prefix}/labels")
    except FileNotFoundError:
        labels_dir = None
    records: list[ImageRecord] = []
    for path in sorted(p for p in images_dir.iterdir() if p.is_file()):
        if path.name.startswith(".") or path.suffix.lower() not in IMAGE_SUFFIXES:
            continue
        file_key = f"{prefix}/images/{path.name}"
        with path.open("rb") as fh:
            width, height = probe_image(
                fh, file_key, settings.max_image_pixels, settings.max_image_decoded_bytes
            )
        labels_path = labels_dir / f"{path.stem}.txt" if labels_dir is not None else None
        labels_key: str | None = None
        detections: list[dict[str, Any]] = []
        if labels_path is not None and labels_path.is_file():
            labels_key = f"{prefix}/labels/{labels_path.name}"
            with labels_path.open("rb") as fh:
                detections = parse_detections(fh, labels_key, classes, settings.max_detection_lines)
        records.append(
            ImageRecord(
                name=path.name,
                file_key=file_key,
                width=width,
                height=height,
                size_bytes=path.stat().st_size,
                labels_key=labels_key,
                detections=detections,
            )
        )
    return records


def record_images(session: Session, snapshot_id: str, records: Sequence[ImageRecord]) -> None:
    """Upsert one SnapshotImage row per record (by name) and drop rows of images no longer
    there, then set the snapshot's counts: running it twice changes nothing."""
    snap = snapshots.get(session, snapshot_id)
    existing = {
        row.name: row
        for row in session.scalars(
            select(SnapshotImage).where(SnapshotImage.snapshot_id == snapshot_id)
        )
    }
    now = utcnow()
    for record in records:
        row = existing.pop(record.name, None)
        if row is None:
            row = SnapshotImage(snapshot_id=snapshot_id, name=record.name)
            session.add(row)
        row.file_key = record.file_key
        row.labels_key = record.labels_key
        row.width, row.height = record.width, record.height
        row.size_bytes = record.size_bytes
        row.detections = list(record.detections)
        row.verified_at = now
    for stale in existing.values():
        session.delete(stale)
    snap.n_images = len(records)
    snap.n_detections = sum(len(r.detections) for r in records)
    session.flush()
