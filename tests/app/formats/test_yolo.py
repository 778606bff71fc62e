"""YOLO label files: the one parser (app/formats/yolo.py)."""

from __future__ import annotations

import io

import pytest

from app.formats import FormatError, FormatTooLarge
from app.formats.yolo import YoloBox, read_class_names, read_yolo, yolo_line


def read(text: bytes, n_classes: int | None = 3, max_boxes: int | None = None) -> list[YoloBox]:
    return read_yolo(io.BytesIO(text), "labels/a.txt", n_classes, max_boxes)


def test_lines_read_with_and_without_confidence_blank_lines_and_a_bom() -> None:
    boxes = read(b"\xef\xbb\xbf0 0.5 0.25 0.1 0.2\n\n  \n2 1 0 0.5 0.5 0.875\n")
    assert boxes == [
        YoloBox(0, 0.5, 0.25, 0.1, 0.2, None),
        YoloBox(2, 1.0, 0.0, 0.5, 0.5, 0.875),
    ]
    assert [yolo_line(b) for b in boxes] == [
        "0 0.500000 0.250000 0.100000 0.200000",
        "2 1.000000 0.000000 0.500000 0.500000 0.875",
    ]
    assert read(b"".join((yolo_line(b) + "\n").encode() for b in boxes)) == boxes


@pytest.mark.parametrize(
    ("text", "code", "message"),
    [
        (b"0 0.5 0.5 0.1 0.1\n0 0.5 0.5 0.1\n", "InvalidDetections",
         "labels/a.txt line 2: expected 5 or 6 numbers"),
        (b"0 0.5 abc 0.1 0.1\n", "InvalidDetections", "line 1: 'abc' is not a number"),
        (b"1.5 0.5 0.5 0.1 0.1\n", "InvalidDetections", "class id '1.5' is not an integer"),
        (b"\n\n3 0.5 0.5 0.1 0.1\n", "UnknownClass", "line 3: class id 3 is not one of the "
         "environment's 3 classes (0..2)"),
        (b"-1 0.5 0.5 0.1 0.1\n", "UnknownClass", "class id -1"),
        (b"0 1.5 0.5 0.1 0.1\n", "InvalidDetections", "cx = 1.5 is outside 0..1"),
        (b"0 0.5 0.5 0.1 0.1 nan\n", "InvalidDetections", "confidence = nan"),
        (b"0 0.5 0.5 0.1 \xff\n", "InvalidDetections", "line 1: not UTF-8 text"),
        (b"0 " + b"0" * 2000 + b"\n", "InvalidDetections", "line 1: longer than 1024 bytes"),
    ],
)  # fmt: skip
def test_a_bad_line_names_the_file_and_line(text: bytes, code: str, message: str) -> None:
    with pytest.raises(FormatError) as err:
        read(text)
    assert err.value.code == code and message in str(err.value), err.value


def test_limits_and_an_unknown_class_count() -> None:
    assert read(b"7 0.5 0.5 0.1 0.1\n", n_classes=None)[0].class_id == 7
    with pytest.raises(FormatError, match="class id -2"):
        read(b"-2 0.5 0.5 0.1 0.1\n", n_classes=None)
    with pytest.raises(FormatTooLarge) as err:
        read(b"0 0.5 0.5 0.1 0.1\n" * 3, max_boxes=2)
    assert err.value.code == "TooManyDetections" and "line 3" in err.value.field


def test_class_names_one_a_line_trailing_blanks_dropped() -> None:
    source = io.BytesIO(b"\xef\xbb\xbfcrate \n drum\n\n\n")
    assert read_class_names(source, "classes.txt") == ["crate", "drum"]
    with pytest.raises(FormatError, match=r"classes\.txt line 2: not UTF-8"):
        read_class_names(io.BytesIO(b"crate\n\xff\n"), "classes.txt")
