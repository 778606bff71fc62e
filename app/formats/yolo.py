"""YOLO label files: the one parser, used by the upload API and the compare stage.

One file per image (``labels/<image stem>.txt``), one detection per line (class names in
``classes.txt``, :func:`read_class_names`)::

    class cx cy w h [confidence]

``class`` is an integer class id (line i of classes.txt names class i); ``cx cy w h`` are
the box centre and size as fractions of the image width and height (0..1); the optional
confidence is 0..1. Blank lines are skipped; a UTF-8 byte-order mark on line 1 is allowed.
Errors are :class:`FormatError` naming the file and line: codes ``InvalidDetections``,
``UnknownClass``, and ``TooManyDetections`` (:class:`FormatTooLarge`).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import BinaryIO

from app.formats.errors import FormatError, FormatTooLarge

CODE = "InvalidDetections"
MAX_LINE_BYTES = 1024
_FIELDS = ("cx", "cy", "w", "h", "confidence")


@dataclass(frozen=True)
class YoloBox:
    """One detection: class id, box centre and size as fractions of the image (0..1), and
    the detector's confidence (0..1; None when the line has none)."""

    class_id: int
    cx: float
    cy: float
    w: float
    h: float
    confidence: float | None


def text_lines(
    source: BinaryIO, where: str, *, code: str = CODE, max_line_bytes: int = MAX_LINE_BYTES
) -> Iterator[tuple[int, str]]:
    """Numbered UTF-8 text lines (from 1), read one at a time with a bounded length;
    :class:`FormatError` (``code``) naming ``where`` and the line otherwise."""
    number = 0
    while raw := source.readline(max_line_bytes + 1):
        number += 1
        if len(raw) > max_line_bytes:
            raise FormatError(
                f"{where} line {number}", f"longer than {max_line_bytes} bytes", code=code
            )
        if number == 1 and raw.startswith(b"\xef\xbb\xbf"):
            raw = raw[3:]
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError:
            raise FormatError(f"{where} line {number}", "not UTF-8 text", code=code) from None
        yield number, text


def read_class_names(source: BinaryIO, where: str) -> list[str]:
    """classes.txt beside the labels: one class name per line, line i naming class id i;
    names stripped of surrounding white space, trailing blank lines dropped. Errors as
    :func:`text_lines`."""
    names = [line.strip() for _, line in text_lines(source, where)]
    while names and not names[-1]:
        names.pop()
    return names


def read_yolo(
    source: BinaryIO, where: str, n_classes: int | None = None, max_boxes: int | None = None
) -> list[YoloBox]:
    """The detections of one label file, in file order.

    With ``n_classes``, class ids must be below it (``UnknownClass``); with ``max_boxes``,
    more detections are :class:`FormatTooLarge` (``TooManyDetections``)."""
    out: list[YoloBox] = []
    for number, line in text_lines(source, where):
        parts = line.split()
        if not parts:
            continue
        at = f"{where} line {number}"
        if max_boxes is not None and len(out) >= max_boxes:
            raise FormatTooLarge(at, f"more than {max_boxes} detections", code="TooManyDetections")
        out.append(parse_yolo_line(parts, at, n_classes))
    return out


def parse_yolo_line(parts: list[str], at: str, n_classes: int | None) -> YoloBox:
    """One line's whitespace-separated tokens as a :class:`YoloBox`; errors name ``at``."""
    if len(parts) not in (5, 6):
        raise FormatError(
            at,
            f"expected 5 or 6 numbers (class cx cy w h [confidence]), got {len(parts)}",
            code=CODE,
        )
    values: list[float] = []
    for token in parts:
        try:
            values.append(float(token))
        except ValueError:
            raise FormatError(at, f"{token!r} is not a number", code=CODE) from None
    if not values[0].is_integer():
        raise FormatError(at, f"class id {parts[0]!r} is not an integer", code=CODE)
    class_id = int(values[0])
    if class_id < 0 or (n_classes is not None and class_id >= n_classes):
        known = "" if n_classes is None else f" of the environment's {n_classes} classes"
        upto = "" if n_classes is None else f" (0..{n_classes - 1})"
        raise FormatError(at, f"class id {class_id} is not one{known}{upto}", code="UnknownClass")
    for name, value in zip(_FIELDS, values[1:], strict=False):
        if not (math.isfinite(value) and 0.0 <= value <= 1.0):
            raise FormatError(at, f"{name} = {value} is outside 0..1", code=CODE)
    cx, cy, w, h = values[1:5]
    return YoloBox(class_id, cx, cy, w, h, values[5] if len(values) == 6 else None)


def yolo_line(box: YoloBox) -> str:
    """The label-file line of one detection (six decimals; confidence three), no newline."""
    text = f"{box.class_id} {box.cx:.6f} {box.cy:.6f} {box.w:.6f} {box.h:.6f}"
    return text if box.confidence is None else f"{text} {box.confidence:.3f}"
