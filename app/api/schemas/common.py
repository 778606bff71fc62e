"""Shapes shared by several resources."""

from __future__ import annotations

from typing import Annotated, Any

from pydantic import AfterValidator, BaseModel, ConfigDict, Field


def _check_pose(value: list[list[float]]) -> list[list[float]]:
    if len(value) != 4 or any(len(row) != 4 for row in value):
        raise ValueError("a pose is a 4×4 row-major nested list")
    last = value[3]
    if any(abs(a - b) > 1e-6 for a, b in zip(last, (0.0, 0.0, 0.0, 1.0), strict=True)):
        raise ValueError("a pose's last row must be [0, 0, 0, 1]")
    return value


Pose = Annotated[list[list[float]], AfterValidator(_check_pose)]
"""4×4 row-major, metres; ``env_from_object`` maps object-model coordinates into the
environment frame."""


class ErrorOut(BaseModel):
    error: str
    detail: str


class Model(BaseModel):
    model_config = ConfigDict(from_attributes=True)


ERRORS: dict[int | str, dict[str, Any]] = {
    401: {"model": ErrorOut, "description": "missing or unknown API key"},
    403: {"model": ErrorOut, "description": "the key lacks the scope"},
    404: {"model": ErrorOut, "description": "not found"},
    422: {"model": ErrorOut, "description": "invalid input, naming the field"},
    429: {
        "model": ErrorOut,
        "description": "too many unknown API keys from this address (Retry-After: seconds)",
        "headers": {"Retry-After": {"schema": {"type": "integer"}}},
    },
}
"""What every ``/v1`` operation may answer besides its own statuses."""
MALFORMED: dict[int | str, dict[str, Any]] = {
    400: {"model": ErrorOut, "description": "a multipart body that cannot be parsed"},
}
TOO_LARGE: dict[int | str, dict[str, Any]] = {
    413: {"model": ErrorOut, "description": "the body is over its size limit"},
}


def conflict(description: str) -> dict[int | str, dict[str, Any]]:
    """A documented 409 (``error`` names which conflict)."""
    return {409: {"model": ErrorOut, "description": description}}


class Readiness(BaseModel):
    status: str = Field(description="ok or unavailable")
    checks: dict[str, str] = Field(description="database and storage: ok or the error")
