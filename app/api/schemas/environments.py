from __future__ import annotations

from datetime import datetime
from typing import Any

from pydantic import BaseModel, Field

from app.api.schemas.common import Model, Pose
from app.core.enums import SnapshotState, TwinStatus
from app.core.environment_summary import Summary
from app.core.models import Environment, TwinInstance
from app.core.twin import Progress


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
        '{"kind": "mean_std", "k": 1.0}, ...}, "retention": {"images_after_days": 30, '
        '"keep_last_snapshots": 10}, "inventory": {"preset": "fast", "band_min_m": 0.006}}: '
        "presets and option overrides of the reconstruct, compare and inventory stages, and "
        "this environment's retention policy over the server's (0: keep); an unknown preset "
        "or option or a value of the wrong type is a 422",
    )


class TwinProgressRead(BaseModel):
    """Where the twin stands against the environment's snapshots: it is brought forward one
    snapshot at a time in ``seq`` order."""

    seq: int = Field(
        description="the newest snapshot seq the twin took into account (applied or "
        "skipped); 0 before any"
    )
    snapshot: str | None = Field(
        description="the newest snapshot whose changes the twin reflects (the 'before' of "
        "the next automatic comparison)"
    )
    status: TwinStatus = Field(
        description="current: every snapshot is in; reconstructing: the next snapshot is "
        "not reconstructed yet; comparing: its automatic comparison is queued or running; "
        "blocked: that comparison failed or was cancelled: POST /v1/comparisons/{id}/retry"
    )
    waiting_for: str | None = Field(description="the next snapshot in seq order, if any")
    comparison: str | None = Field(description="that snapshot's automatic comparison, once made")

    @classmethod
    def of(cls, progress: Progress) -> TwinProgressRead:
        return cls(
            seq=progress.seq,
            snapshot=progress.snapshot_id,
            status=progress.status,
            waiting_for=progress.waiting_for,
            comparison=progress.comparison_id,
        )


class LastSnapshotRead(BaseModel):
    """The environment's newest snapshot (not deleted)."""

    id: str
    seq: int
    state: SnapshotState
    created_at: datetime


class EnvironmentRead(Model):
    id: str
    name: str
    classes: list[str]
    reference: dict[str, Any] | None
    options: dict[str, Any]
    created_at: datetime
    twin: TwinProgressRead
    twin_object_count: int = Field(description="objects the twin holds now (open instances)")
    last_snapshot: LastSnapshotRead | None = Field(
        description="the newest snapshot with its state; null before any"
    )

    @classmethod
    def of(cls, env: Environment, progress: Progress, summary: Summary) -> EnvironmentRead:
        last = summary.last_snapshot
        return cls(
            id=env.id,
            name=env.name,
            classes=env.classes,
            reference=env.reference,
            options=env.options,
            created_at=env.created_at,
            twin=TwinProgressRead.of(progress),
            twin_object_count=summary.twin_object_count,
            last_snapshot=None
            if last is None
            else LastSnapshotRead(
                id=last.id,
                seq=last.seq,
                state=SnapshotState(last.state),
                created_at=last.created_at,
            ),
        )


class InstanceRead(BaseModel):
    instance_id: str
    external_id: str | None = Field(
        default=None, description="the twin platform's own id of the object, when it has one"
    )
    object: str
    object_id: str | None
    pose: Pose | None
    pose_quality: dict[str, Any] | None
    since_snapshot: str | None = Field(
        description="the snapshot since which the pose holds (null: seeded or corrected "
        "before the twin reflected any snapshot)"
    )
    created_snapshot: str | None = Field(
        description="the snapshot the instance belongs to from its creation (null: seeded "
        "before the twin reflected any snapshot; it stands from the start)"
    )
    created_at: datetime
    last_seen_snapshot: str | None = Field(
        default=None,
        description="the newest snapshot whose inventory showed the instance (null: none "
        "has; only in the state)",
    )
    seen: bool | None = Field(
        default=None,
        description="whether the snapshot the state reflects showed it (false: the cameras "
        "did not see it, its state is kept as it was; only in the state)",
    )

    @classmethod
    def of(cls, i: TwinInstance) -> InstanceRead:
        return cls(
            instance_id=i.id,
            external_id=i.external_id,
            object=i.object_name,
            object_id=i.object_id,
            pose=i.pose,
            pose_quality=i.pose_quality,
            since_snapshot=i.since_snapshot_id,
            created_snapshot=i.created_snapshot_id,
            created_at=i.created_at,
        )


class InstanceSeed(BaseModel):
    """One instance the twin platform already knows."""

    object: str = Field(
        min_length=1,
        max_length=200,
        description="one of the environment's classes, by name or by its library object id",
    )
    pose: list[list[float]] = Field(
        description="env_from_object: 4×4 row-major, metres, in the environment frame; a "
        "finite rigid transform (rotation orthonormal within 1e-3, determinant +1, last row "
        "0 0 0 1), stored with its rotation block made exactly orthonormal"
    )
    external_id: str | None = Field(
        default=None,
        max_length=200,
        description="the platform's own id of the object: unique among the environment's "
        "open instances; 1 to 200 characters, no control characters or surrounding spaces",
    )


class InstanceCorrection(BaseModel):
    """What to correct on an instance: any of the three; a field left out is unchanged."""

    object: str | None = Field(
        default=None, min_length=1, max_length=200, description="a class name or library id"
    )
    pose: list[list[float]] | None = Field(default=None, description="as InstanceSeed.pose")
    external_id: str | None = Field(
        default=None, max_length=200, description="the platform's id; null clears it"
    )


class TwinStateRead(BaseModel):
    environment: str
    objects: list[InstanceRead]
    twin: TwinProgressRead = Field(
        description="where the twin stands now; without at_snapshot, the snapshot this "
        "state reflects"
    )
    at_snapshot: str | None = Field(
        default=None,
        description="the snapshot asked for with ?snapshot=: objects are the twin as it "
        "stood once that snapshot was taken into account (null: as it stands)",
    )


class PoseRecord(BaseModel):
    snapshot: str | None = Field(
        description="the snapshot the record belongs to (null: made by hand before the twin "
        "reflected any snapshot)"
    )
    comparison: str | None
    change_type: str = Field(
        description="a comparison's change (added, removed, moved, swapped), a change made "
        "through the API (seeded, corrected, retired) or an inventory's (inventoried: found "
        "by a snapshot's inventory; drifted: its pose moved beyond the estimate's noise; "
        "restored: reopened, since the snapshot whose comparison removed it still shows it)"
    )
    pose: Pose | None
    at: datetime


class InstanceHistory(BaseModel):
    instance_id: str
    external_id: str | None = None
    object: str
    created_snapshot: str | None
    closed_snapshot: str | None
    poses: list[PoseRecord]
