"""Stage fractions become one overall, monotonic job progress."""

from __future__ import annotations

import pytest

from workers.progress import weighted


def test_weighted_progress_spans_stages_in_order_and_never_goes_back() -> None:
    seen: list[tuple[str, float]] = []
    report = weighted(lambda stage, fraction: seen.append((stage, fraction)), {"a": 1, "b": 3})
    report("a", 0.5)
    report("b", 0.0)
    report("b.detail", 0.5)  # a sub-stage counts as its parent
    report("unknown", 0.9)  # keeps the overall figure
    report("a", 0.0)  # never backwards
    report("b", 1.0)
    assert [f for _, f in seen] == pytest.approx([0.125, 0.25, 0.625, 0.625, 0.625, 1.0])
    assert [s for s, _ in seen] == ["a", "b", "b.detail", "unknown", "a", "b"]
