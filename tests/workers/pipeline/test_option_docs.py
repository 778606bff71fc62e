"""docs/options.md is written from the option classes: comments, types, defaults, presets."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from workers.pipeline import option_docs


@dataclass(frozen=True)
class _Inner:
    k: float = 1.0


@dataclass(frozen=True)
class _Options:
    """Options of a made-up stage."""

    seed: int = 0
    # sampling
    # points drawn from the mesh, before thinning
    n_points: int = 6000
    kind: Literal["a", "b"] = "a"
    scales_m: tuple[float, ...] = (0.02, 0.01)  # coarse to fine
    # refinement
    iterations: int = 20  # per scale; raise when ICP stops early
    limit: float | None = None
    inner: _Inner = field(default_factory=_Inner)


def test_comment_above_a_field_is_its_meaning_and_a_short_first_line_its_group() -> None:
    comments = option_docs.field_comments(_Options)
    assert comments["seed"] == ("", "")
    assert comments["n_points"] == ("sampling", "points drawn from the mesh, before thinning")
    assert comments["scales_m"] == ("sampling", "coarse to fine")
    assert comments["iterations"] == ("refinement", "per scale; raise when ICP stops early")
    assert comments["limit"] == ("refinement", "")


def test_types_defaults_and_presets_are_rendered_as_a_reader_writes_them() -> None:
    rows = {f.name: f for f in option_docs.field_docs(_Options)}
    assert (rows["kind"].type_text, rows["kind"].default_text) == ('"a" | "b"', '"a"')
    assert (rows["scales_m"].type_text, rows["scales_m"].default_text) == (
        "list of float",
        "[0.02, 0.01]",
    )
    assert (rows["limit"].type_text, rows["limit"].default_text) == ("float | null", "null")
    assert rows["inner"].default_text == "_Inner()"
    lines = option_docs.preset_lines({"default": _Options(), "big": _Options(n_points=9)})
    assert lines == ["- `default`: the defaults", "- `big`: `n_points` 9"]


def test_every_option_class_is_documented_field_by_field() -> None:
    text = option_docs.option_docs()
    for spec in option_docs.OPTION_CLASSES:
        assert f"## {spec.title}" in text
    assert "| `planar_prior` | bool |" in text
