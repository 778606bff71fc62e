"""Typed errors of the pure pipeline.

Every public pipeline function raises a subclass of :class:`PipelineError` on failure
(never returns None). ``code`` is a stable machine-readable string that the worker copies
into the job row (``job.error.code``); ``detail`` is what a person can act on.
"""

from __future__ import annotations


class PipelineError(Exception):
    """Base of every pipeline failure. ``code`` is stable, ``detail`` is human-readable."""

    code: str = "PipelineError"

    def __init__(self, detail: str, *, code: str | None = None) -> None:
        super().__init__(detail)
        self.detail = detail
        if code is not None:
            self.code = code

    def __str__(self) -> str:
        return f"{self.code}: {self.detail}"


class ShapeError(PipelineError):
    """An array argument has the wrong shape or dtype (a programming error upstream)."""

    code = "ShapeError"


class InputError(PipelineError):
    """Input files or values are unusable (unreadable image, bad model file, ...)."""

    code = "InvalidInput"


class ReconstructionError(PipelineError):
    """Structure-from-motion, dense stereo or frame alignment failed."""

    code = "ReconstructionFailed"


class ComparisonError(PipelineError):
    """Change detection or identification failed."""

    code = "ComparisonFailed"


class RegistrationError(PipelineError):
    """Pose estimation (global registration + ICP) failed."""

    code = "RegistrationFailed"


class Cancelled(PipelineError):
    """Raised by a progress callback to stop a stage that the user cancelled."""

    code = "Cancelled"
