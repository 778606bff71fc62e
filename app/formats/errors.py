"""The one error type of the file formats: a :class:`FormatError` names where in which
document the problem is, so the API can answer 422 (413 for :class:`FormatTooLarge`) and a
pipeline stage can raise its InputError, each with the same text."""

from __future__ import annotations

from typing import Any


class FormatError(ValueError):
    """A document does not follow its format.

    ``field`` is where: the document and the path inside it (``cameras.json:
    intrinsics_per_image['a.jpg']``, ``labels/a.txt line 3``); ``problem`` is what is wrong;
    ``code`` is the stable machine code the API answers with (``InvalidCameras``,
    ``InvalidDetections``, ``UnknownClass``). ``str(error)`` is ``"<field>: <problem>"``.
    """

    def __init__(self, field: str, problem: str, *, code: str) -> None:
        super().__init__(f"{field}: {problem}")
        self.field = field
        self.problem = problem
        self.code = code

    @property
    def detail(self) -> str:
        """The full message: ``"<field>: <problem>"``."""
        return str(self)


class FormatTooLarge(FormatError):
    """A document is over a size or count limit (the API answers 413)."""


def short(text: str, limit: int = 40) -> str:
    """``text``, or its two ends when longer than ``limit`` (so a 5,000-digit value is never
    echoed back)."""
    return text if len(text) <= limit else f"{text[:20]}…{text[-10:]} ({len(text)} characters)"


def show(value: Any, limit: int = 40) -> str:
    """A short ``repr`` of ``value`` for an error message (never the 400 digits of 10**400:
    a caller may pass what did not come through a strict JSON loader)."""
    if isinstance(value, int) and not isinstance(value, bool) and value.bit_length() > 64:
        return f"an integer of {value.bit_length()} bits"
    return short(repr(value), limit)
