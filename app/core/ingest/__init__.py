"""Snapshot ingest: validate an uploaded capture, store it, queue its job; and the worker's
first stage, which re-reads the stored capture with the same parsers.

An upload is either loose files (``images``, ``detections``, optional ``cameras``) or one
archive (.zip, .tar, .tar.gz) holding the same files anywhere inside it. Everything is
streamed in chunks into a private staging folder (archives member by member, never trusting
declared sizes), validated there, and moved under ``snapshots/<id>/`` only once it all
passed::

    snapshots/<id>/images/<name>        JPEG or PNG
    snapshots/<id>/labels/<stem>.txt    YOLO: class cx cy w h [confidence], 0..1
    snapshots/<id>/cameras.json         optional (app/formats/cameras.py)

A rejected upload raises a :class:`~app.core.errors.DomainError` naming the file (and line)
and leaves nothing behind. The same ``Idempotency-Key`` with the same files (by name and
SHA-256) returns the first snapshot and job; with other files it is a 409.

One module per concern: :mod:`.images` (image checks), :mod:`.parsers` (cameras.json, YOLO
labels and classes.txt through :mod:`app.formats`), :mod:`.staging` (the staging folder and
each file's limits), :mod:`.archives` (zip and tar members, bombs), :mod:`.upload` (the
request: validate, insert, queue), :mod:`.records` (the worker's re-read and its rows).
"""

from app.core.ingest.common import CAMERAS_NAME, CLASSES_NAME, IMAGE_SUFFIXES, TASK
from app.core.ingest.images import probe_image
from app.core.ingest.parsers import parse_cameras, parse_classes, parse_detections
from app.core.ingest.records import ImageRecord, read_capture, record_images
from app.core.ingest.staging import STAGING, UploadPart, sweep_staging
from app.core.ingest.upload import Ingested, UploadFiles, create_snapshot

__all__ = [
    "CAMERAS_NAME",
    "CLASSES_NAME",
    "IMAGE_SUFFIXES",
    "STAGING",
    "TASK",
    "ImageRecord",
    "Ingested",
    "UploadFiles",
    "UploadPart",
    "create_snapshot",
    "parse_cameras",
    "parse_classes",
    "parse_detections",
    "probe_image",
    "read_capture",
    "record_images",
    "sweep_staging",
]
