"""Snapshot ingest: validate an uploaded capture, store it, queue its job; and the worker's
first stage, which re-reads the stored capture with the same parsers.

An upload is either loose files (``images``, ``detections``, optional ``cameras``) or one
archive (.zip, .tar, .tar.gz) holding the same files anywhere inside it. Everything is
streamed in chunks into a private staging folder (archives member by member, never trusting
declared sizes), validated there, and moved under ``snapshots/<id>/`` only once it all
passed::

    snapshots/<id>/images/<name>        JPEG or PNG
    snapshots/<id>/labels/<stem>.txt    YOLO: class cx cy w h [confidence], 0..1
    snapshots/<id>/cameras.json         optional

A rejected upload raises a :class:`~app.core.errors.DomainError` naming the file (and line)
and leaves nothing behind. The same ``Idempotency-Key`` with the same files (by name and
SHA-256) returns the first snapshot and job; with other files it is a 409.
"""

from __future__ import annotations

import errno
import fcntl
import hashlib
import math
import os
import re
import shutil
import stat
import struct
import tarfile
import time
import uuid
import zipfile
import zlib
from collections.abc import Callable, Collection, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any, BinaryIO

from PIL import Image, UnidentifiedImageError
from sqlalchemy import event, func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from app.core import environments, jobs, jsondoc, snapshots
from app.core.enums import JobKind, SnapshotState
from app.core.errors import (
    Conflict,
    DomainError,
    InsufficientStorage,
    InvalidInput,
    PayloadTooLarge,
    UnsupportedMedia,
)
from app.core.models import Environment, Job, Snapshot, SnapshotImage, new_id, utcnow
from app.core.settings import Settings
from app.core.storage import LocalStorage

TASK = "snapshot.process"
IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png"}
IMAGE_FORMATS = {"JPEG", "PNG"}
LABEL_SUFFIX = ".txt"
CAMERAS_NAME = "cameras.json"
CLASSES_NAME = "classes.txt"
CAMERAS_MAX_BYTES = 32 * 1024**2
CLASSES_MAX_BYTES = 1024**2
MAX_LINE_BYTES = 1024
CAMERA_MODELS = {"PINHOLE": 4, "SIMPLE_RADIAL": 4, "OPENCV": 8}
MAX_IMAGE_SIDE = 1_000_000  # pixels: far past any camera, and safe as a 32-bit int
_SEQ_RETRIES = 5
_CONTROL = re.compile(r"[\x00-\x1f\x7f]")


# --- error codes (each names the file and, for text, the line) ------------------------------


def _invalid(code: str, detail: str) -> InvalidInput:
    return InvalidInput(detail, code=code)


def _too_large(code: str, detail: str) -> PayloadTooLarge:
    return PayloadTooLarge(detail, code=code)


# --- data shapes ----------------------------------------------------------------------------


@dataclass(frozen=True)
class UploadPart:
    """One uploaded file as the service sees it: the client's file name and a readable
    stream (a spooled temporary file; read in chunks, never whole)."""

    filename: str
    source: BinaryIO


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


@dataclass
class _Staged:
    path: Path
    where: str  # the name the client knows the file by (archive member or upload name)
    size: int
    sha256: str


@dataclass
class _Staging:
    """Files written to the staging folder so far, with the request's running totals."""

    root: Path
    settings: Settings
    images: dict[str, _Staged] = field(default_factory=dict)  # by file name
    image_stems: dict[str, str] = field(default_factory=dict)  # stem -> file name
    labels: dict[str, _Staged] = field(default_factory=dict)  # by stem
    cameras: _Staged | None = None
    classes: list[str] | None = None
    classes_sha256: str | None = None
    n_files: int = 0
    n_bytes: int = 0
    # Called with the current file's bytes so far, per chunk: an archive's inflation check.
    budget: Callable[[int], None] | None = None

    def digest(self) -> str:
        """SHA-256 over the sorted (stored name, content SHA-256) pairs: the same files give
        the same digest whether sent loose or in any archive."""
        entries = [(f"images/{n}", s.sha256) for n, s in self.images.items()]
        entries += [(f"labels/{stem}.txt", s.sha256) for stem, s in self.labels.items()]
        if self.cameras is not None:
            entries.append((CAMERAS_NAME, self.cameras.sha256))
        if self.classes_sha256 is not None:
            entries.append((CLASSES_NAME, self.classes_sha256))
        h = hashlib.sha256()
        for name, sha in sorted(entries):
            h.update(f"{name}\0{sha}\n".encode())
        return h.hexdigest()


@dataclass(frozen=True)
class Ingested:
    """The outcome of an upload: the snapshot, its job, and whether this request made them
    (False for an idempotent replay)."""

    snapshot: Snapshot
    job: Job
    created: bool


# --- parsers shared by the upload and the worker's re-read ---------------------------------


def probe_image(
    source: BinaryIO, where: str, max_pixels: int, max_decoded_bytes: int | None = None
) -> tuple[int, int]:
    """Width and height of a JPEG or PNG after checking that it decodes.

    The pixel count and the decoded size (width × height × channels × bytes per sample, at
    least 3 bytes a pixel: readers decode to 8-bit colour) come from the header
    (``Image.open`` reads nothing else) and are checked against ``max_pixels`` and
    ``max_decoded_bytes`` before any decoding; JPEGs decode at 1/8 scale (``Image.draft``);
    PNGs are verified (chunk CRCs) and their pixel stream inflated in pieces and counted, so
    memory stays small whatever the size. ``ImageTooLarge`` (413) or ``InvalidImage`` (422);
    details never show server paths.
    """
    try:
        with Image.open(source) as img:
            fmt = img.format
            width, height = img.size
            if fmt not in IMAGE_FORMATS:
                raise _invalid("InvalidImage", f"{where}: not a JPEG or PNG image ({fmt})")
            _check_pixels(width, height, where, max_pixels)
            if max_decoded_bytes is not None:
                per_pixel = _png_pixel_bytes(source) if fmt == "PNG" else len(img.getbands())
                _check_decoded(width, height, max(3, per_pixel), where, max_decoded_bytes)
            if fmt == "JPEG":
                img.draft(img.mode, (max(1, width // 8), max(1, height // 8)))
                img.load()
            else:
                img.verify()
        if fmt == "PNG":
            _check_png_pixels(source, where)
    except Image.DecompressionBombError as exc:
        raise _too_large("ImageTooLarge", f"{where}: {_reason(exc)}") from exc
    except DomainError:
        raise
    except (
        UnidentifiedImageError,
        OSError,
        SyntaxError,
        ValueError,
        EOFError,
        struct.error,
        zlib.error,
    ) as exc:
        raise _invalid(
            "InvalidImage", f"{where}: not a readable JPEG or PNG ({_reason(exc)})"
        ) from exc
    return width, height


# A file object's repr (``<_io.BufferedReader name='/srv/...'>``) or an absolute path.
_SERVER_PATH = re.compile(
    r"<_io\.\w+ name=(?:'[^']*'|\"[^\"]*\"|\S+?)>|(?<![\w.])/(?:[^\s/'\"<>:]+/)+[^\s/'\"<>:]*"
)


def _reason(exc: BaseException) -> str:
    """An exception's message for a client: server paths removed (never show them)."""
    text = _SERVER_PATH.sub("the file", str(exc)).strip()
    return text or type(exc).__name__


def _png_pixel_bytes(source: BinaryIO) -> int:
    """Bytes a decoded pixel takes, from the PNG's IHDR (channels × bytes per sample;
    palette images decode to RGBA)."""
    at = source.tell()
    source.seek(16)
    head = source.read(10)
    source.seek(at)
    if len(head) < 10:
        return 4
    depth, color = head[8], head[9]
    channels = 4 if color == 3 else _PNG_CHANNELS.get(color, 4)
    return channels * (2 if depth > 8 else 1)


def _check_decoded(width: int, height: int, per_pixel: int, where: str, limit: int) -> None:
    decoded = width * height * per_pixel
    if decoded > limit:
        raise _too_large(
            "ImageTooLarge",
            f"{where}: {width}×{height} at {per_pixel} bytes a pixel decodes to {decoded} "
            f"bytes, more than the limit of {limit}",
        )


_PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}
_ADAM7 = (
    (0, 0, 8, 8),
    (4, 0, 8, 8),
    (0, 4, 4, 8),
    (2, 0, 4, 4),
    (0, 2, 2, 4),
    (1, 0, 2, 2),
    (0, 1, 1, 2),
)


def _png_raw_size(width: int, height: int, bit_depth: int, color_type: int, interlace: int) -> int:
    """Bytes of the filtered scanlines a PNG header promises (PNG spec, section 7-8)."""
    bits = _PNG_CHANNELS.get(color_type, 4) * bit_depth
    passes = _ADAM7 if interlace else ((0, 0, 1, 1),)
    total = 0
    for x0, y0, dx, dy in passes:
        w, h = -(-(width - x0) // dx), -(-(height - y0) // dy)
        if w > 0 and h > 0:
            total += h * (1 + (w * bits + 7) // 8)
    return total


def _check_png_pixels(source: BinaryIO, where: str) -> None:
    """Inflate a PNG's IDAT stream piece by piece and check it holds exactly the scanline
    bytes its header promises (the chunk CRCs were checked by ``verify``)."""
    source.seek(8)
    inflater = zlib.decompressobj()
    expected, produced = 0, 0
    while True:
        head = source.read(8)
        if len(head) < 8:
            raise _invalid("InvalidImage", f"{where}: truncated PNG")
        length, kind = struct.unpack(">I4s", head)
        if kind == b"IHDR":
            width, height, depth, color, _, _, interlace = struct.unpack(
                ">IIBBBBB", source.read(13)
            )
            expected = _png_raw_size(width, height, depth, color, interlace)
            source.seek(length - 13, 1)
        elif kind == b"IDAT":
            left = length
            while left:
                piece = source.read(min(left, 1024 * 1024))
                if not piece:
                    raise _invalid("InvalidImage", f"{where}: truncated PNG")
                left -= len(piece)
                while piece:
                    produced += len(inflater.decompress(piece, 1024 * 1024))
                    piece = inflater.unconsumed_tail
                    if produced > expected:
                        raise _invalid("InvalidImage", f"{where}: more pixel data than its size")
        elif kind == b"IEND":
            break
        else:
            source.seek(length, 1)
        source.seek(4, 1)  # the CRC
    if not inflater.eof or produced != expected:
        raise _invalid(
            "InvalidImage", f"{where}: pixel data ends early ({produced} of {expected} bytes)"
        )


def _check_pixels(width: int, height: int, where: str, max_pixels: int) -> None:
    if width <= 0 or height <= 0:
        raise _invalid("InvalidImage", f"{where}: empty image ({width}×{height})")
    if width * height > max_pixels:
        raise _too_large(
            "ImageTooLarge",
            f"{where}: {width}×{height} = {width * height} pixels, more than the limit "
            f"of {max_pixels}",
        )


def parse_detections(
    source: BinaryIO, where: str, classes: Sequence[str], max_lines: int
) -> list[dict[str, Any]]:
    """YOLO lines ``class cx cy w h [confidence]`` → detection dicts
    ``{"class_id", "class", "cx", "cy", "w", "h", "confidence"}`` (confidence None when
    absent). Blank lines are skipped. Errors name ``where`` and the line number:
    ``InvalidDetections``, ``UnknownClass`` (422), ``TooManyDetections`` (413)."""
    out: list[dict[str, Any]] = []
    for number, line in _lines(source, where):
        parts = line.split()
        if not parts:
            continue
        if len(out) >= max_lines:
            raise _too_large(
                "TooManyDetections", f"{where} line {number}: more than {max_lines} detections"
            )
        if len(parts) not in (5, 6):
            raise _invalid(
                "InvalidDetections",
                f"{where} line {number}: expected 5 or 6 numbers "
                f"(class cx cy w h [confidence]), got {len(parts)}",
            )
        values: list[float] = []
        for token in parts:
            try:
                values.append(float(token))
            except ValueError:
                raise _invalid(
                    "InvalidDetections", f"{where} line {number}: {token!r} is not a number"
                ) from None
        raw_class = values[0]
        if not raw_class.is_integer():
            raise _invalid(
                "InvalidDetections",
                f"{where} line {number}: class id {parts[0]!r} is not an integer",
            )
        class_id = int(raw_class)
        if not 0 <= class_id < len(classes):
            raise _invalid(
                "UnknownClass",
                f"{where} line {number}: class id {class_id} is not one of the environment's "
                f"{len(classes)} classes (0..{len(classes) - 1})",
            )
        names = ("cx", "cy", "w", "h", "confidence")
        for name, value in zip(names, values[1:], strict=False):
            if not (math.isfinite(value) and 0.0 <= value <= 1.0):
                raise _invalid(
                    "InvalidDetections",
                    f"{where} line {number}: {name} = {value} is outside 0..1",
                )
        cx, cy, w, h = values[1:5]
        out.append(
            {
                "class_id": class_id,
                "class": classes[class_id],
                "cx": cx,
                "cy": cy,
                "w": w,
                "h": h,
                "confidence": values[5] if len(values) == 6 else None,
            }
        )
    return out


def _lines(source: BinaryIO, where: str) -> Iterator[tuple[int, str]]:
    """Numbered text lines, read one at a time with a bounded length."""
    number = 0
    while raw := source.readline(MAX_LINE_BYTES + 1):
        number += 1
        if len(raw) > MAX_LINE_BYTES:
            raise _invalid(
                "InvalidDetections",
                f"{where} line {number}: longer than {MAX_LINE_BYTES} bytes",
            )
        if number == 1 and raw.startswith(b"\xef\xbb\xbf"):
            raw = raw[3:]
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError:
            raise _invalid("InvalidDetections", f"{where} line {number}: not UTF-8 text") from None
        yield number, text


def parse_cameras(source: BinaryIO, where: str, image_names: Collection[str]) -> dict[str, Any]:
    """Validate cameras.json: ``intrinsics`` and/or ``intrinsics_per_image`` (model
    PINHOLE | SIMPLE_RADIAL | OPENCV with 4, 4, 8 params, positive width and height), and
    optional ``poses`` (4×4 rigid ``env_from_cam`` per image). Every named image must exist.
    Returns the normalised document; ``InvalidCameras`` (422) otherwise."""
    data = source.read(CAMERAS_MAX_BYTES + 1)
    if len(data) > CAMERAS_MAX_BYTES:
        raise _too_large("PayloadTooLarge", f"{where}: larger than {CAMERAS_MAX_BYTES} bytes")
    # Strict JSON: NaN, 1e400, 5,000-digit numbers and deep nesting are InvalidCameras too.
    doc = jsondoc.loads(data, where, code="InvalidCameras")
    if not isinstance(doc, dict):
        raise _invalid("InvalidCameras", f"{where}: expected a JSON object")
    unknown = sorted(set(doc) - {"intrinsics", "intrinsics_per_image", "poses"})
    if unknown:
        raise _invalid("InvalidCameras", f"{where}: unknown keys {unknown}")
    if "intrinsics" not in doc and "intrinsics_per_image" not in doc:
        raise _invalid("InvalidCameras", f"{where}: give 'intrinsics' or 'intrinsics_per_image'")
    out: dict[str, Any] = {}
    if "intrinsics" in doc:
        out["intrinsics"] = _check_intrinsics(doc["intrinsics"], f"{where}: intrinsics")
    if "intrinsics_per_image" in doc:
        per_image = _named_map(doc["intrinsics_per_image"], where, "intrinsics_per_image")
        out["intrinsics_per_image"] = {
            name: _check_intrinsics(value, f"{where}: intrinsics_per_image[{name!r}]")
            for name, value in per_image.items()
        }
        _check_names(per_image, image_names, where, "intrinsics_per_image")
    if "poses" in doc:
        poses = _named_map(doc["poses"], where, "poses")
        _check_names(poses, image_names, where, "poses")
        checked: dict[str, list[list[float]]] = {}
        for name, pose in poses.items():
            try:
                checked[name] = environments.check_rigid(pose, f"{where}: poses[{name!r}]")
            except InvalidInput as exc:
                raise _invalid("InvalidCameras", exc.detail) from exc
        out["poses"] = checked
    return out


def _named_map(value: Any, where: str, key: str) -> dict[str, Any]:
    if not isinstance(value, dict) or not value:
        raise _invalid("InvalidCameras", f"{where}: {key} must be a non-empty object by image name")
    return value


def _check_names(named: dict[str, Any], image_names: Collection[str], where: str, key: str) -> None:
    missing = sorted(set(named) - set(image_names))
    if missing:
        raise _invalid(
            "InvalidCameras", f"{where}: {key} names images that were not uploaded: {missing[:5]}"
        )


def _check_intrinsics(value: Any, where: str) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise _invalid("InvalidCameras", f"{where}: expected {{model, width, height, params}}")
    model = value.get("model")
    if not isinstance(model, str) or model not in CAMERA_MODELS:
        raise _invalid(
            "InvalidCameras",
            f"{where}: model {jsondoc.show(model)} is not one of {sorted(CAMERA_MODELS)}",
        )
    size = []
    for key in ("width", "height"):
        dim = value.get(key)
        if not isinstance(dim, int) or isinstance(dim, bool) or not 0 < dim <= MAX_IMAGE_SIDE:
            raise _invalid(
                "InvalidCameras",
                f"{where}: {key} must be a positive integer (at most {MAX_IMAGE_SIDE})",
            )
        size.append(dim)
    params = value.get("params")
    expected = CAMERA_MODELS[model]
    if not isinstance(params, list) or len(params) != expected:
        raise _invalid(
            "InvalidCameras",
            f"{where}: model {model} takes {expected} params, got {jsondoc.show(params)}",
        )
    if not all(
        isinstance(p, int | float)
        and not isinstance(p, bool)
        and abs(p) < jsondoc.INT_LIMIT
        and math.isfinite(p)
        for p in params
    ):
        raise _invalid("InvalidCameras", f"{where}: params must be finite numbers")
    return {
        "model": model,
        "width": size[0],
        "height": size[1],
        "params": [float(p) for p in params],
    }


def parse_classes(source: BinaryIO, where: str, classes: Sequence[str]) -> list[str]:
    """classes.txt (one name per line) must list the environment's classes in order;
    ``ClassesMismatch`` (422) names the first line that differs."""
    names = [line.strip() for _, line in _lines(source, where)]
    while names and not names[-1]:
        names.pop()
    for number, (got, want) in enumerate(zip(names, classes, strict=False), start=1):
        if got != want:
            raise _invalid(
                "ClassesMismatch",
                f"{where} line {number}: {got!r}, but the environment's class {number - 1} "
                f"is {want!r}",
            )
    if len(names) != len(classes):
        raise _invalid(
            "ClassesMismatch",
            f"{where}: {len(names)} classes, the environment has {len(classes)}",
        )
    return names


# --- staging --------------------------------------------------------------------------------


def _file_name(raw: str, where: str) -> str:
    """The base name of an uploaded file; rejects empty, control characters, dot names."""
    name = raw.replace("\\", "/").rsplit("/", 1)[-1]
    if not name or name.startswith(".") or _CONTROL.search(name) or len(name.encode()) > 255:
        raise _invalid("InvalidFileName", f"{where}: {raw!r} is not a usable file name")
    return name


def _stage_file(staging: _Staging, kind: str, name: str, where: str, source: BinaryIO) -> _Staged:
    """Copy ``source`` into the staging folder in chunks, within the per-file and per-request
    byte limits and the file-count limit."""
    settings = staging.settings
    staging.n_files += 1
    if staging.n_files > settings.max_upload_files:
        raise _too_large(
            "TooManyFiles", f"{where}: more than {settings.max_upload_files} files in one upload"
        )
    remaining = settings.max_upload_bytes - staging.n_bytes
    limit = min(settings.max_file_bytes, remaining)
    target = staging.root / kind / name if kind else staging.root / name
    digest = hashlib.sha256()
    size = 0
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        with target.open("wb") as out:
            while chunk := source.read(1024 * 1024):
                size += len(chunk)
                if size > limit:
                    if limit == settings.max_file_bytes:
                        detail = f"{where}: larger than {settings.max_file_bytes} bytes"
                    else:
                        detail = (
                            f"{where}: the upload is larger than {settings.max_upload_bytes} bytes"
                        )
                    raise _too_large("PayloadTooLarge", detail)
                if staging.budget is not None:
                    staging.budget(size)
                digest.update(chunk)
                out.write(chunk)
    except OSError as exc:
        if _disk_full(exc):  # not the archive's fault: a clean 507, never "damaged"
            raise _no_space(where) from exc
        raise
    staging.n_bytes += size
    return _Staged(path=target, where=where, size=size, sha256=digest.hexdigest())


def _add(staging: _Staging, raw_name: str, where: str, source: BinaryIO, role: str | None) -> None:
    """Stage one file by its role (``images``, ``detections``, ``cameras``) or, for archive
    members (role None), by its name: images by suffix, ``cameras.json``, ``classes.txt``,
    other ``.txt`` files as detections."""
    name = _file_name(raw_name, where)
    lower = name.lower()
    suffix = PurePosixPath(lower).suffix
    if role == "detections" and lower == CLASSES_NAME:
        role = "classes"  # YOLO exports put classes.txt beside the labels
    if role is None:
        if lower == CAMERAS_NAME:
            role = "cameras"
        elif lower == CLASSES_NAME:
            role = "classes"
        elif suffix in IMAGE_SUFFIXES:
            role = "images"
        elif suffix == LABEL_SUFFIX:
            role = "detections"
        else:
            raise UnsupportedMedia(
                f"{where}: unsupported file type (images are .jpg .jpeg .png, detections .txt, "
                "plus optional cameras.json and classes.txt)",
                code="UnsupportedFileType",
            )
    if role == "images":
        if suffix not in IMAGE_SUFFIXES:
            raise UnsupportedMedia(
                f"{where}: images must be .jpg, .jpeg or .png", code="UnsupportedFileType"
            )
        stem = PurePosixPath(name).stem
        clash = staging.image_stems.get(stem)
        if clash is not None:
            raise _invalid(
                "DuplicateImage", f"{where}: another image ({clash}) has the same stem {stem!r}"
            )
        staging.image_stems[stem] = name
        staging.images[name] = _stage_file(staging, "images", name, where, source)
    elif role == "detections":
        if suffix != LABEL_SUFFIX:
            raise UnsupportedMedia(
                f"{where}: detections must be YOLO .txt files", code="UnsupportedFileType"
            )
        stem = PurePosixPath(name).stem
        if stem in staging.labels:
            raise _invalid("DuplicateDetections", f"{where}: a second detection file for {stem!r}")
        staging.labels[stem] = _stage_file(staging, "labels", f"{stem}.txt", where, source)
    elif role == "cameras":
        if staging.cameras is not None:
            raise _invalid("InvalidCameras", f"{where}: a second cameras.json")
        staging.cameras = _stage_file(staging, "", CAMERAS_NAME, where, source)
    else:  # classes.txt: checked against the environment, not stored
        if staging.classes_sha256 is not None:
            raise _invalid("ClassesMismatch", f"{where}: a second classes.txt")
        staged = _stage_file(staging, "", ".classes.txt", where, source)
        staging.classes_sha256 = staged.sha256


def _unsafe(member: str, why: str) -> InvalidInput:
    return _invalid("UnsafeArchiveMember", f"archive member {member!r}: {why}")


def _member_path(name: str) -> PurePosixPath | None:
    """A safe relative member path, or None for entries to skip (folders, macOS extras)."""
    norm = name.replace("\\", "/")
    path = PurePosixPath(norm)
    if norm.startswith("/") or re.match(r"^[A-Za-z]:", norm):
        raise _unsafe(name, "absolute path")
    if ".." in path.parts:
        raise _unsafe(name, "path with '..'")
    if "\x00" in norm:
        raise _unsafe(name, "NUL in the name")
    if not path.parts or norm.endswith("/"):
        return None
    if "__MACOSX" in path.parts or path.name.startswith(".") or path.name == "Thumbs.db":
        return None
    return path


# Inflation allowed beyond ``max_archive_ratio`` × the compressed bytes: small archives of
# text (labels, tar headers) compress far better than photos.
ARCHIVE_SLACK_BYTES = 1024**2


def _bomb(where: str, inflated: int, packed: int, ratio: float) -> PayloadTooLarge:
    return _too_large(
        "ArchiveBomb",
        f"{where}: inflates to {inflated} bytes from {packed} compressed bytes, more than "
        f"{ratio:g} times (max_archive_ratio)",
    )


def _too_many_members(where: str, limit: int) -> PayloadTooLarge:
    return _too_large(
        "TooManyFiles", f"{where}: more than {limit} archive members (folders count too)"
    )


def _zip_entries(source: BinaryIO) -> int | None:
    """The member count the zip's end record declares, read before the central directory
    is parsed into memory; None when there is no readable end record."""
    try:
        end = zipfile._EndRecData(source)  # type: ignore[attr-defined]
    except (OSError, ValueError, struct.error):
        return None
    finally:
        source.seek(0)
    if not end:
        return None
    return int(end[zipfile._ECD_ENTRIES_TOTAL])  # type: ignore[attr-defined]


def _stage_zip(staging: _Staging, source: BinaryIO, where: str) -> None:
    settings = staging.settings
    declared_entries = _zip_entries(source)
    if declared_entries is not None and declared_entries > settings.max_archive_members:
        raise _too_many_members(where, settings.max_archive_members)
    try:
        archive = zipfile.ZipFile(source)
    except (zipfile.BadZipFile, OSError, ValueError) as exc:
        raise _invalid("InvalidArchive", f"{where}: not a readable zip ({_reason(exc)})") from exc
    with archive:
        infos = archive.infolist()
        if len(infos) > settings.max_archive_members:
            raise _too_many_members(where, settings.max_archive_members)
        files = [i for i in infos if not i.is_dir()]
        if len(files) > settings.max_upload_files:
            raise _too_large(
                "TooManyFiles",
                f"{where}: {len(files)} members, more than {settings.max_upload_files}",
            )
        declared = sum(i.file_size for i in files)
        if declared > settings.max_upload_bytes:
            raise _too_large(
                "PayloadTooLarge",
                f"{where}: unpacks to {declared} bytes, more than {settings.max_upload_bytes}",
            )
        # A member never inflates past its declared size (zipfile stops there and checks
        # the CRC), so the declared sizes bound what can be written: check them first.
        packed = sum(i.compress_size for i in files)
        if declared > settings.max_archive_ratio * packed + ARCHIVE_SLACK_BYTES:
            raise _bomb(where, declared, packed, settings.max_archive_ratio)
        for info in infos:
            mode = info.external_attr >> 16
            if mode and stat.S_IFMT(mode) not in (0, stat.S_IFREG, stat.S_IFDIR):
                raise _unsafe(info.filename, "not a regular file (link or device)")
            path = _member_path(info.filename)
            if path is None or info.is_dir():
                continue
            if info.flag_bits & 0x1:
                raise _invalid("InvalidArchive", f"{where}: member {info.filename!r} is encrypted")
            try:
                with archive.open(info) as member:
                    _add(staging, path.name, info.filename, member, None)  # type: ignore[arg-type]
            except (zipfile.BadZipFile, zlib.error, OSError, NotImplementedError) as exc:
                raise _invalid(
                    "InvalidArchive",
                    f"{where}: member {info.filename!r} is damaged ({_reason(exc)})",
                ) from exc


class _CountingReader:
    """Counts the bytes read from a stream: how much of a compressed archive was consumed."""

    def __init__(self, raw: BinaryIO) -> None:
        self.raw = raw
        self.n = 0

    def read(self, size: int = -1) -> bytes:
        data = self.raw.read(size)
        self.n += len(data)
        return data


def _stage_tar(staging: _Staging, source: BinaryIO, where: str) -> None:
    settings = staging.settings
    counted = _CountingReader(source)

    def budget(current: int) -> None:
        # Checked per chunk while extracting: stop at the limit, not after the bomb landed.
        inflated = staging.n_bytes + current
        if inflated > settings.max_archive_ratio * counted.n + ARCHIVE_SLACK_BYTES:
            raise _bomb(where, inflated, counted.n, settings.max_archive_ratio)

    staging.budget = budget
    try:
        with tarfile.open(fileobj=counted, mode="r|*") as archive:  # type: ignore[call-overload]
            for n_members, member in enumerate(archive, start=1):
                # Every member counts (folders too), and none is kept: a stream of headers
                # costs neither memory nor time without limit.
                archive.members = []
                if n_members > settings.max_archive_members:
                    raise _too_many_members(where, settings.max_archive_members)
                if not (member.isfile() or member.isdir()):
                    raise _unsafe(member.name, "not a regular file (link or device)")
                path = _member_path(member.name)
                if path is None or member.isdir():
                    continue
                extracted = archive.extractfile(member)
                if extracted is None:
                    raise _unsafe(member.name, "not a regular file")
                with extracted:
                    _add(staging, path.name, member.name, extracted, None)
    except (tarfile.TarError, EOFError, zlib.error, OSError) as exc:
        raise _invalid("InvalidArchive", f"{where}: not a readable tar ({_reason(exc)})") from exc
    finally:
        staging.budget = None


def _stage_archive(staging: _Staging, archive: UploadPart) -> None:
    where = archive.filename or "archive"
    lower = where.lower()
    if lower.endswith(".zip"):
        _stage_zip(staging, archive.source, where)
    elif lower.endswith((".tar", ".tar.gz", ".tgz")):
        _stage_tar(staging, archive.source, where)
    else:
        raise UnsupportedMedia(
            f"{where}: the archive must be .zip, .tar or .tar.gz", code="UnsupportedFileType"
        )


# --- validation -----------------------------------------------------------------------------


@dataclass(frozen=True)
class _Checked:
    n_detections: int


def _validate(staging: _Staging, classes: Sequence[str]) -> _Checked:
    """Every check that needs the whole capture: counts, orphans, images, detections,
    cameras and classes.txt."""
    settings = staging.settings
    if len(staging.images) < settings.min_images:
        raise _invalid(
            "TooFewImages",
            f"{len(staging.images)} images; a snapshot needs at least {settings.min_images}",
        )
    for stem, labels in sorted(staging.labels.items()):
        if stem not in staging.image_stems:
            raise _invalid("OrphanDetections", f"{labels.where}: no image with the stem {stem!r}")
    # Decoders release the GIL: probe a few images at once; the first error in upload order.
    pool = ThreadPoolExecutor(max_workers=min(4, os.cpu_count() or 1))
    try:
        probes = [
            pool.submit(
                _probe_path, image, settings.max_image_pixels, settings.max_image_decoded_bytes
            )
            for image in staging.images.values()
        ]
        for probe in probes:
            probe.result()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
    n_detections = 0
    for labels in staging.labels.values():
        with labels.path.open("rb") as fh:
            n_detections += len(
                parse_detections(fh, labels.where, classes, settings.max_detection_lines)
            )
    if staging.cameras is not None:
        with staging.cameras.path.open("rb") as fh:
            parse_cameras(fh, staging.cameras.where, staging.images.keys())
    classes_file = staging.root / ".classes.txt"
    if classes_file.exists():
        with classes_file.open("rb") as fh:
            parse_classes(fh, CLASSES_NAME, classes)
        classes_file.unlink()
    return _Checked(n_detections=n_detections)


def _probe_path(image: _Staged, max_pixels: int, max_decoded: int) -> tuple[int, int]:
    with image.path.open("rb") as fh:
        return probe_image(fh, image.where, max_pixels, max_decoded)


# --- the upload -----------------------------------------------------------------------------


def create_snapshot(
    session: Session,
    storage: LocalStorage,
    settings: Settings,
    environment_id: str,
    *,
    images: Sequence[UploadPart] = (),
    detections: Sequence[UploadPart] = (),
    cameras: UploadPart | None = None,
    archive: UploadPart | None = None,
    idempotency_key: str | None = None,
    lookup: sessionmaker[Session] | None = None,
) -> Ingested:
    """Validate and store an uploaded capture, insert its snapshot (state ``uploaded``, the
    environment's next ``seq``) and queue ``snapshot.process`` after commit.

    Give loose files (``images``, ``detections``, ``cameras``) or one ``archive``. Errors are
    DomainErrors naming the file and line; nothing is stored when one is raised; a full disk
    is a 507 ``InsufficientStorage``.

    ``lookup`` opens short read-only sessions for what is read before the files are checked
    (the environment, an earlier request with the same ``Idempotency-Key``). The API gives
    one, so that ``session`` touches the database only for the insert: on SQLite its write
    lock is then held for milliseconds, not while the files are staged and checked. Without
    it, ``session`` does the reads too.
    """
    with _reading(session, lookup) as reader:
        env = environments.get(reader, environment_id)
        env_id, classes = env.id, list(env.classes)
    if archive is not None and (images or detections or cameras is not None):
        raise _invalid(
            "InvalidUpload", "send either an archive or images/detections/cameras, not both"
        )
    if archive is None and not images:
        raise _invalid("InvalidUpload", "no images: send 'images' files or one 'archive'")
    if idempotency_key is not None and not 0 < len(idempotency_key) <= 200:
        raise _invalid("InvalidUpload", "Idempotency-Key: 1 to 200 characters")

    sweep_staging(storage)
    with _staging_dir(storage) as staging_dir:
        staging = _Staging(root=staging_dir, settings=settings)
        if archive is not None:
            _stage_archive(staging, archive)
        else:
            for part in images:
                _add(staging, part.filename, part.filename, part.source, "images")
            for part in detections:
                _add(staging, part.filename, part.filename, part.source, "detections")
            if cameras is not None:
                _add(
                    staging,
                    CAMERAS_NAME,
                    cameras.filename or CAMERAS_NAME,
                    cameras.source,
                    "cameras",
                )
        digest = staging.digest()
        if idempotency_key is not None:
            with _reading(session, lookup) as reader:
                replay = _replay(reader, env_id, idempotency_key, digest)
            if replay is not None and lookup is not None:
                replay = _replay(session, env_id, idempotency_key, digest)  # in this session
            if replay is not None:
                return replay
        checked = _validate(staging, classes)
        return _insert(session, storage, env_id, staging, checked, idempotency_key, digest)


@contextmanager
def _reading(session: Session, lookup: sessionmaker[Session] | None) -> Iterator[Session]:
    """``session``, or a short read-only session of ``lookup`` (closed, never committed)."""
    if lookup is None:
        yield session
        return
    with lookup() as reader:
        yield reader


# --- staging folders ------------------------------------------------------------------------

STAGING = ".tmp"
_STALE_UNLOCKED_S = 3600.0


def _disk_full(exc: OSError) -> bool:
    return exc.errno in (errno.ENOSPC, errno.EDQUOT)


def _no_space(where: str) -> InsufficientStorage:
    return InsufficientStorage(
        f"{where}: the server's storage is full; nothing of this upload was kept, try again later"
    )


@contextmanager
def _staging_dir(storage: LocalStorage) -> Iterator[Path]:
    """A private staging folder ``.tmp/<id>``, removed on the way out. While it exists this
    process holds an exclusive ``flock`` on ``.tmp/<id>.lock``: the kernel drops the lock
    when the process dies, which is how :func:`sweep_staging` tells an abandoned folder (an
    API killed mid-upload) from one in use by another process."""
    base = storage.path(STAGING)
    name = uuid.uuid4().hex
    lock_path, root = base / f"{name}.lock", base / name
    try:
        base.mkdir(parents=True, exist_ok=True)
        fd = os.open(lock_path, os.O_CREAT | os.O_RDWR, 0o600)
    except OSError as exc:
        if _disk_full(exc):
            raise _no_space("upload") from exc
        raise
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        try:
            root.mkdir()
        except OSError as exc:
            if _disk_full(exc):
                raise _no_space("upload") from exc
            raise
        yield root
    finally:
        shutil.rmtree(root, ignore_errors=True)
        lock_path.unlink(missing_ok=True)
        os.close(fd)


def sweep_staging(storage: LocalStorage) -> int:
    """Remove staging folders whose process is gone (their lock is free), and unlocked
    leftovers older than an hour; returns how many were removed. Safe beside live uploads
    in other processes: a held lock is never taken."""
    base = storage.path(STAGING)
    if not base.is_dir():
        return 0
    removed = 0
    for lock_path in base.glob("*.lock"):
        try:
            fd = os.open(lock_path, os.O_RDWR)
        except FileNotFoundError:
            continue
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                continue  # a live upload
            shutil.rmtree(base / lock_path.stem, ignore_errors=True)
            lock_path.unlink(missing_ok=True)
            removed += 1
        finally:
            os.close(fd)
    cutoff = time.time() - _STALE_UNLOCKED_S
    for folder in base.iterdir():
        if (
            folder.is_dir()
            and not (base / f"{folder.name}.lock").exists()
            and folder.stat().st_mtime < cutoff
        ):
            shutil.rmtree(folder, ignore_errors=True)
            removed += 1
    return removed


def _replay(session: Session, environment_id: str, key: str, digest: str) -> Ingested | None:
    """The snapshot an earlier request with this key made, when the files are the same;
    409 ``IdempotencyKeyReused`` when they differ; None when the key is new."""
    snap = session.scalar(
        select(Snapshot).where(
            Snapshot.environment_id == environment_id, Snapshot.idempotency_key == key
        )
    )
    if snap is None:
        return None
    if snap.request_digest != digest:
        raise Conflict(
            f"Idempotency-Key {key!r} was used for snapshot {snap.id} with different files",
            code="IdempotencyKeyReused",
        )
    job = snapshots.job_of(session, snap.id)
    if job is None:  # the job is created in the snapshot's transaction; never expected
        raise Conflict(f"snapshot {snap.id} has no job", code="IdempotencyKeyReused")
    return Ingested(snapshot=snap, job=job, created=False)


def _insert(
    session: Session,
    storage: LocalStorage,
    env_id: str,
    staging: _Staging,
    checked: _Checked,
    idempotency_key: str | None,
    digest: str,
) -> Ingested:
    # Serialise uploads to one environment (PostgreSQL row lock; SQLite has one writer).
    session.execute(select(Environment.id).where(Environment.id == env_id).with_for_update())
    env = environments.get(session, env_id)  # 404 if it went while the files were checked
    snapshot_id = new_id()
    prefix = f"snapshots/{snapshot_id}"
    snap: Snapshot | None = None
    for _ in range(_SEQ_RETRIES):
        if idempotency_key is not None:
            replay = _replay(session, env.id, idempotency_key, digest)
            if replay is not None:
                return replay
        seq = (
            session.scalar(select(func.max(Snapshot.seq)).where(Snapshot.environment_id == env.id))
            or 0
        ) + 1
        candidate = Snapshot(
            id=snapshot_id,
            environment_id=env.id,
            seq=seq,
            state=SnapshotState.uploaded,
            idempotency_key=idempotency_key,
            request_digest=digest,
            storage_prefix=prefix,
            n_images=len(staging.images),
            n_detections=checked.n_detections,
            upload_bytes=staging.n_bytes,
            has_cameras=staging.cameras is not None,
            cameras_key=f"{prefix}/{CAMERAS_NAME}" if staging.cameras is not None else None,
        )
        try:
            with session.begin_nested():
                session.add(candidate)
                session.flush()
        except IntegrityError:  # a concurrent upload took the seq or the key: look again
            continue
        snap = candidate
        break
    if snap is None:
        raise Conflict(
            f"environment {env.id}: too many concurrent uploads, try again",
            code="ConcurrentUpload",
        )
    try:
        storage.move_in(staging.root, prefix)
        job = jobs.create(
            session, JobKind.snapshot, TASK, environment_id=env.id, snapshot_id=snap.id
        )
    except BaseException:
        storage.delete_prefix(prefix)
        raise
    # The files are in place before the row is committed (a reader never sees a row without
    # its files); if the transaction rolls back instead (a failed commit, an error after
    # this), they go with it.
    session.info.setdefault(_MOVED_IN, []).append((storage, prefix))
    return Ingested(snapshot=snap, job=job, created=True)


_MOVED_IN = "twindelta_ingest_moved_in"


@event.listens_for(Session, "after_commit")
def _keep_moved_in(session: Session) -> None:
    if not session.in_nested_transaction():
        session.info.pop(_MOVED_IN, None)


@event.listens_for(Session, "after_soft_rollback")
def _remove_moved_in(session: Session, previous_transaction: Any) -> None:
    if previous_transaction.parent is None:  # the outermost rollback, not a SAVEPOINT's
        for storage, prefix in session.info.pop(_MOVED_IN, []):
            storage.delete_prefix(prefix)


# --- the worker's ingest stage --------------------------------------------------------------


def read_capture(
    storage: LocalStorage, prefix: str, classes: Sequence[str], settings: Settings
) -> list[ImageRecord]:
    """Re-read a stored capture: each image's size (checked as on upload) and its detections,
    sorted by image name. Raises the upload's DomainErrors if the files changed since."""
    images_dir = storage.path(f"{prefix}/images")
    records: list[ImageRecord] = []
    for path in sorted(p for p in images_dir.iterdir() if p.is_file()):
        if path.name.startswith(".") or path.suffix.lower() not in IMAGE_SUFFIXES:
            continue
        file_key = f"{prefix}/images/{path.name}"
        with storage.open(file_key) as fh:
            width, height = probe_image(
                fh, file_key, settings.max_image_pixels, settings.max_image_decoded_bytes
            )
        labels_key: str | None = f"{prefix}/labels/{path.stem}.txt"
        detections: list[dict[str, Any]] = []
        if labels_key is not None and storage.exists(labels_key):
            with storage.open(labels_key) as fh:
                detections = parse_detections(fh, labels_key, classes, settings.max_detection_lines)
        else:
            labels_key = None
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
