"""Content negotiation: which of the media types a route offers an ``Accept`` header prefers."""

from __future__ import annotations

import math
from collections.abc import Sequence

from app.core.errors import DomainError


class NotAcceptable(DomainError):
    """406: the ``Accept`` header allows none of the media types the resource has."""

    status_code = 406
    code = "NotAcceptable"


def choose(accept: str | None, offered: Sequence[str]) -> str:
    """The offered media type ``accept`` ranks highest (RFC 9110: the most specific matching
    range gives a type its weight; ties go to the earlier offer, so ``offered[0]`` is the
    default for a missing header or ``*/*``). NotAcceptable when every offer has weight 0."""
    if accept is None or not accept.strip():
        return offered[0]
    ranges = [_parse(part) for part in accept.split(",") if part.strip()]
    best, best_q = None, 0.0
    for media_type in offered:
        q = _weight(media_type, ranges)
        if q > best_q:
            best, best_q = media_type, q
    if best is None:
        raise NotAcceptable(
            f"Accept: {accept[:200]!r} allows none of {', '.join(offered)}; ask for one of "
            "them (or use the format query parameter)"
        )
    return best


def _parse(part: str) -> tuple[str, float]:
    media_range, *params = (p.strip() for p in part.split(";"))
    q = 1.0
    for param in params:
        name, _, value = param.partition("=")
        if name.strip().lower() == "q":
            try:
                q = float(value)
            except ValueError:
                q = 0.0
            q = min(max(q, 0.0), 1.0) if math.isfinite(q) else 0.0
    return media_range.lower(), q


def _weight(media_type: str, ranges: list[tuple[str, float]]) -> float:
    kind = media_type.split("/", 1)[0]
    for pattern in (media_type, f"{kind}/*", "*/*"):
        weights = [q for r, q in ranges if r == pattern]
        if weights:
            return max(weights)
    return 0.0
