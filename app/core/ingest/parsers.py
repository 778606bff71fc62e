"""The upload's text formats, read with the shared readers of :mod:`app.formats` and their
errors answered as the API's: a :class:`~app.formats.FormatError` becomes InvalidInput (422),
a :class:`~app.formats.FormatTooLarge` PayloadTooLarge (413), with the same code and text."""

from __future__ import annotations

from collections.abc import Collection, Iterator, Sequence
from contextlib import contextmanager
from typing import Any, BinaryIO

from app.core import jsondoc
from app.core.errors import DomainError, InvalidInput, PayloadTooLarge
from app.core.ingest.common import CAMERAS_MAX_BYTES, _invalid, _too_large
from app.formats import FormatError, FormatTooLarge
from app.formats.cameras import CODE as CAMERAS_CODE
from app.formats.cameras import read_cameras
from app.formats.yolo import read_class_names, read_yolo


def domain_error(exc: FormatError) -> DomainError:
    """The API's answer to a format error: 413 when over a limit, else 422."""
    if isinstance(exc, FormatTooLarge):
        return PayloadTooLarge(exc.detail, code=exc.code)
    return InvalidInput(exc.detail, code=exc.code)


@contextmanager
def answered() -> Iterator[None]:
    """Raise a :class:`FormatError` from the block as the API's DomainError."""
    try:
        yield
    except FormatError as exc:
        raise domain_error(exc) from exc


def parse_detections(
    source: BinaryIO, where: str, classes: Sequence[str], max_lines: int
) -> list[dict[str, Any]]:
    """YOLO lines ``class cx cy w h [confidence]`` → detection dicts
    ``{"class_id", "class", "cx", "cy", "w", "h", "confidence"}`` (confidence None when
    absent). Blank lines are skipped. Errors name ``where`` and the line number:
    ``InvalidDetections``, ``UnknownClass`` (422), ``TooManyDetections`` (413)."""
    with answered():
        boxes = read_yolo(source, where, len(classes), max_lines)
    return [
        {
            "class_id": box.class_id,
            "class": classes[box.class_id],
            "cx": box.cx,
            "cy": box.cy,
            "w": box.w,
            "h": box.h,
            "confidence": box.confidence,
        }
        for box in boxes
    ]


def parse_cameras(source: BinaryIO, where: str, image_names: Collection[str]) -> dict[str, Any]:
    """Validate cameras.json with :func:`app.formats.cameras.read_cameras` after the strict
    JSON load (NaN, 1e400, 5,000-digit numbers and deep nesting are refused too). Every
    named image must be in ``image_names``. Returns the normalised document;
    ``InvalidCameras`` (422) or ``PayloadTooLarge`` (413) otherwise."""
    data = source.read(CAMERAS_MAX_BYTES + 1)
    if len(data) > CAMERAS_MAX_BYTES:
        raise _too_large("PayloadTooLarge", f"{where}: larger than {CAMERAS_MAX_BYTES} bytes")
    doc = jsondoc.loads(data, where, code=CAMERAS_CODE)
    with answered():
        return read_cameras(doc, where, image_names).to_json()


def parse_classes(source: BinaryIO, where: str, classes: Sequence[str]) -> list[str]:
    """classes.txt (one name per line) must list the environment's classes in order;
    ``ClassesMismatch`` (422) names the first line that differs."""
    with answered():
        names = read_class_names(source, where)
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
