"""PLY header counts against the file size (app.formats.ply), shared by the object upload and
the worker that loads the model."""

from __future__ import annotations

from app.formats.ply import ply_count_problem

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
