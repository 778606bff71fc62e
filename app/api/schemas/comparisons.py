from __future__ import annotations

from collections.abc import Mapping
from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, Field

from app.api.schemas.common import Model, Pose
from app.core.enums import ComparisonState
from app.core.models import Comparison


class ComparisonCreate(BaseModel):
    before: str = Field(description="snapshot id")
    after: str = Field(description="snapshot id")
    options: dict[str, Any] | None = Field(
        default=None,
        description='compare preset and options, e.g. {"preset": "lod"} or {"threshold": '
        '{"kind": "mean_std", "k": 1.0}}; an unknown preset or option or a value of the wrong '
        "type is a 422",
    )


class ChangeRead(Model):
    id: str
    type: str
    object: str | None
    instance_id: str | None
    external_id: str | None = Field(
        default=None,
        description="the twin platform's id of the instance the change matched (seeded or "
        "corrected), when it has one",
    )
    pose: Pose | None
    previous_pose: Pose | None
    replaced_object: str | None
    replaced_instance_id: str | None = None
    replaced_external_id: str | None = Field(
        default=None, description="swapped: the platform's id of the instance it replaced"
    )
    centroid_env: list[float] | None = None
    identification: dict[str, Any] | None
    cluster: dict[str, Any] | None
    pose_quality: dict[str, Any] | None


class ComparisonRead(BaseModel):
    id: str
    environment: str
    before: str
    after: str
    job: str
    state: ComparisonState
    automatic: bool
    applied_to_twin: bool = Field(
        description="its changes are in the twin (automatic comparisons only, applied in "
        "snapshot seq order)"
    )
    applied_at: datetime | None
    created_at: datetime
    completed_at: datetime | None
    options: dict[str, Any]
    distances: dict[str, Any]
    changes: list[ChangeRead]
    clusters: list[dict[str, Any]]

    @classmethod
    def of(cls, c: Comparison, external_ids: Mapping[str, str] | None = None) -> ComparisonRead:
        """``external_ids``: instance id → platform id (``twin_records.external_ids``)."""
        ext = external_ids or {}
        return cls(
            id=c.id,
            environment=c.environment_id,
            before=c.before_id,
            after=c.after_id,
            job=c.job_id,
            state=c.state,
            automatic=c.automatic,
            applied_to_twin=bool(c.applied_to_state),
            applied_at=c.applied_at,
            created_at=c.created_at,
            completed_at=c.completed_at,
            options=c.options,
            distances=c.distances,
            changes=[
                ChangeRead(
                    id=ch.id,
                    type=ch.type,
                    object=ch.object_name,
                    instance_id=ch.instance_id,
                    external_id=ext.get(ch.instance_id or ""),
                    pose=ch.pose,
                    previous_pose=ch.previous_pose,
                    replaced_object=ch.replaced_object,
                    replaced_instance_id=ch.replaced_instance_id,
                    replaced_external_id=ext.get(ch.replaced_instance_id or ""),
                    centroid_env=ch.centroid_env,
                    identification=ch.identification,
                    cluster=ch.cluster,
                    pose_quality=ch.pose_quality,
                )
                for ch in c.changes
            ],
            clusters=c.clusters,
        )


class ClusterPointsRead(BaseModel):
    id: int
    side: Literal["added", "removed"] = Field(
        description="added: points of the after cloud; removed: of the before cloud"
    )
    change_id: str | None = Field(description="the change it is evidence of, if any")
    n_points: int = Field(description="the cluster's points in full")
    positions: list[float] = Field(
        description="x, y, z, x, y, z, ...: environment frame, metres, 4 decimals; all the "
        "points, or 20 000 drawn with a fixed seed"
    )


class ClustersRead(BaseModel):
    clusters: list[ClusterPointsRead]


class ChangeViewRead(BaseModel):
    """One photo that saw the change's cluster (pixels of that photo)."""

    image: str
    outline_px: list[list[float]] = Field(
        description="[[u, v], ...]: convex hull of the cluster's projected visible points"
    )
    box_px: list[float] = Field(description="[x0, y0, x1, y1]: the cluster's box in the photo")
    detection_box_px: list[float] | None = Field(
        description="the photo's detection of the change's class overlapping the box best"
    )
    iou: float | None = Field(description="IoU of box_px and detection_box_px")
    counted: bool = Field(description="the photo counted as an overlap for that class")
