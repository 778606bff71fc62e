from __future__ import annotations

from datetime import datetime
from typing import Any

from pydantic import BaseModel, Field

from app.api.schemas.common import Model, Pose


class EnvironmentCreate(BaseModel):
    name: str = Field(min_length=1, max_length=200)
    classes: list[str] = Field(
        min_length=1, description="classes[i] is the name of detector class id i"
    )
    reference: dict[str, Any] | None = Field(
        default=None,
        description='{"markers": {"dictionary": "DICT_4X4_50", "size": 0.15, '
        '"poses": {"<id>": <4×4 env_from_marker>}}}',
    )
    options: dict[str, Any] | None = Field(
        default=None,
        description='{"reconstruct": {"preset": "default", ...}, "compare": {"threshold": '
        '{"kind": "mean_std", "k": 1.0}, ...}}: presets and option overrides of the two '
        "stages; an unknown preset or option or a value of the wrong type is a 422",
    )


class EnvironmentRead(Model):
    id: str
    name: str
    classes: list[str]
    reference: dict[str, Any] | None
    options: dict[str, Any]
    created_at: datetime


class InstanceRead(BaseModel):
    instance_id: str
    object: str
    object_id: str | None
    pose: Pose | None
    pose_quality: dict[str, Any] | None
    since_snapshot: str
    created_snapshot: str
    created_at: datetime


class TwinStateRead(BaseModel):
    environment: str
    objects: list[InstanceRead]


class PoseRecord(BaseModel):
    snapshot: str
    comparison: str | None
    change_type: str
    pose: Pose | None
    at: datetime


class InstanceHistory(BaseModel):
    instance_id: str
    object: str
    created_snapshot: str
    closed_snapshot: str | None
    poses: list[PoseRecord]
