"""The inventory of a snapshot: every library object it shows (GET /snapshots/{id}/objects)."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, Field

from app.api.schemas.common import Pose
from app.core.models import SnapshotObject


class SnapshotObjectRead(BaseModel):
    """One library object the snapshot's inventory found."""

    object: str = Field(description="the class (library object name)")
    object_id: str | None = Field(description="the library object's id")
    pose: Pose | None = Field(
        description="4×4 env_from_object, metres, row-major (null: the class has no prepared "
        "model to pose it with)"
    )
    verified: bool = Field(
        description="the pose passed the pose stage's checks (fit, coverage, re-projection)"
    )
    pose_quality: dict[str, Any] | None = Field(
        description="the pose stage's figures: fitness, inlier_rmse (m), cluster_coverage, "
        "runner_up_ratio, rotation_slack_deg, final_turn_deg, visible_fitness, chosen_by, "
        "verified, reasons, reprojection {mean_iou, views, passed}"
    )
    identification: dict[str, Any] = Field(
        description="the compare stage's identification figures of its class: metric "
        "(mean IoU × overlaps / occurrences), iou, overlaps, occurrences; model_metric, the "
        "same metric of the posed model's points, when the segment alone scored under the "
        "identification threshold (a flat object's segment, loosened by the smear at its "
        "foot) and the posed model named it"
    )
    centroid_env: list[float] = Field(description="centre of the object, environment frame, m")
    support: str | None = Field(description="the surface it stands on: floor, surface_1, ...")
    instance_id: str | None = Field(
        description="the twin instance it is (null until the twin reached this snapshot, or "
        "when the twin did not take it)"
    )
    external_id: str | None = Field(
        default=None, description="that instance's id in the twin platform, when it has one"
    )

    @classmethod
    def of(cls, row: SnapshotObject, external_ids: dict[str, str]) -> SnapshotObjectRead:
        return cls(
            object=row.object_name,
            object_id=row.object_id,
            pose=row.pose,
            verified=bool((row.pose_quality or {}).get("verified")),
            pose_quality=row.pose_quality,
            identification=row.identification,
            centroid_env=row.centroid_env,
            support=row.support,
            instance_id=row.instance_id,
            external_id=external_ids.get(row.instance_id or ""),
        )
