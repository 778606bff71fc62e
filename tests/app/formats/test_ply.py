"""The one PLY header parser (app.formats.ply): counts against the file size, the parsed
header, the leading vertex element and the scalar table, shared by every PLY reader."""

from __future__ import annotations

import pytest

from app.formats import FormatError
from app.formats.ply import (
    PLY_SCALARS,
    PlyProperty,
    PlyScalar,
    ply_body_problem,
    ply_count_problem,
    read_ply_header,
    vertex_element,
)

HEAD = (
    b"ply\nformat %s 1.0\nelement vertex %d\nproperty float x\nproperty float y\n"
    b"property float z\nend_header\n"
)


def test_counts_within_the_file_pass() -> None:
    head = HEAD % (b"binary_little_endian", 2)
    assert ply_count_problem(head, len(head) + 2 * 12) is None
    ascii_head = HEAD % (b"ascii", 1)
    assert ply_count_problem(ascii_head, len(ascii_head) + len(b"0 0 0\n")) is None


def test_counts_past_the_file_are_named() -> None:
    head = HEAD % (b"binary_little_endian", 2_000_000_000)
    problem = ply_count_problem(head, len(head) + 100)
    assert problem is not None and "2000000000 vertex elements" in problem
    assert "24000000000 bytes" in problem and "holds 100 after its header" in problem


def test_malformed_headers_are_problems() -> None:
    assert ply_count_problem(b"ply\nformat ascii 1.0\n", 100) is not None
    assert "has no count" in (ply_count_problem(b"ply\nelement vertex +5\nend_header\n", 99) or "")
    unknown = b"ply\nelement vertex 1\nproperty quad x\nend_header\n"
    assert "unknown PLY property type 'quad'" in (ply_count_problem(unknown, 99) or "")


def test_the_header_is_parsed_with_its_lists_and_length() -> None:
    head = (
        b"ply\r\nformat binary_big_endian 1.0\r\ncomment made by hand\r\nelement vertex 2\r\n"
        b"property double x\r\nproperty float32 y\r\nproperty float z\r\nproperty uchar red\r\n"
        b"element face 1\r\nproperty list uchar int vertex_indices\r\nend_header\r\n"
    )
    header = read_ply_header(head + b"\0" * 10)
    assert (header.fmt, header.version, header.header_bytes) == (
        "binary_big_endian",
        "1.0",
        len(head),
    )
    vertex, face = header.elements
    assert (vertex.name, vertex.count, face.name, face.count) == ("vertex", 2, "face", 1)
    assert header.fields(vertex) == [("x", ">f8"), ("y", ">f4"), ("z", ">f4"), ("red", ">u1")]
    assert face.properties == (PlyProperty("vertex_indices", "int", "uchar"),)
    assert not face.scalar_only and vertex_element(header) is vertex
    # each element on its own: 2 vertices × (8 + 4 + 4 + 1) bytes, a face at least its length
    assert ply_body_problem(header, len(head) + 34) is None
    assert "2 vertex elements, which need at least 34 bytes" in (
        ply_body_problem(header, len(head) + 33) or ""
    )


@pytest.mark.parametrize(
    ("head", "words"),
    [
        (b"solid x\nend_header\n", "not a PLY file"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nend_header", "has no line end"),
        (b"ply\nformat ascii 2.0\nelement face 1\nproperty list uchar quad v\nend_header\n",
         "unknown PLY property type 'quad'"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float\nend_header\n",
         "cannot read the header line 'property float'"),
        (b"ply\nformat ascii 1.0\nproperty float x\nend_header\n", "cannot read the header line"),
        (b"ply\nformat ascii 1.0\nelement vertex\nend_header\n", "cannot read the header line"),
        (b"ply\nformat utf8 1.0\nend_header\n", "unknown PLY format 'utf8'"),
    ],
)  # fmt: skip
def test_what_one_of_the_former_parsers_let_through_is_refused(head: bytes, words: str) -> None:
    with pytest.raises(FormatError, match=words):
        read_ply_header(head, "cloud.ply", code="InvalidScan")
    assert words in (ply_count_problem(head, 10**6) or "")


@pytest.mark.parametrize(
    ("elements", "words"),
    [
        (b"element vertex 1\nproperty float x\nproperty float y\n", "no vertex element with x"),
        (b"element face 0\nproperty list uchar int v\nelement vertex 1\nproperty float x\n"
         b"property float y\nproperty float z\n", "must come first"),
        (b"element vertex 1\nproperty float x\nproperty float y\nproperty float z\n"
         b"property list uchar int v\n", "list properties in 'vertex'"),
    ],
)  # fmt: skip
def test_the_vertex_element_comes_first_with_xyz_and_no_lists(elements: bytes, words: str) -> None:
    header = read_ply_header(b"ply\nformat ascii 1.0\n" + elements + b"end_header\n")
    with pytest.raises(FormatError, match=words) as caught:
        vertex_element(header, "scan", code="InvalidScan")
    assert caught.value.code == "InvalidScan" and caught.value.field == "scan"


def test_the_scalar_table_has_sizes_and_numpy_codes() -> None:
    assert (PLY_SCALARS["uchar"], PLY_SCALARS["int16"]) == (PlyScalar(1, "u1"), PlyScalar(2, "i2"))
    assert PLY_SCALARS["double"] == PLY_SCALARS["float64"] == PlyScalar(8, "f8")
    assert all(s.size == int(s.code[1:]) for s in PLY_SCALARS.values()) and len(PLY_SCALARS) == 16
