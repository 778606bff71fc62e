"""The published JSON Schema (2020-12) of what a CloudEvents subscription receives: the whole
structured CloudEvent, and each event type's ``data`` under ``$defs/<event type>``.

Every CloudEvent names its data's schema in ``dataschema``
(``urn:twindelta:events:1#/$defs/<type>``: this document's ``$id`` and a JSON Pointer), and
the API serves the document at ``GET /v1/webhooks/schemas/events``; the file
``openapi/events.schema.json`` is :func:`schema_text` (``make lint`` checks it is fresh).

The schema is open to additions (fields may be added to an event without a new version, as
``docs/contract.md`` allows); the tests validate real events against it with every object
closed, so a field the schema does not describe fails them.
"""

from __future__ import annotations

import json
import sys
from typing import Any

from app.core.enums import ChangeType, EventType, JobKind, JobState, TwinUpdate

EVENTS_SCHEMA_ID = "urn:twindelta:events:1"


def dataschema(event_type: str) -> str:
    """The ``dataschema`` URI of an event type's data (this schema's ``$id`` + pointer)."""
    return f"{EVENTS_SCHEMA_ID}#/$defs/{event_type}"


def _obj(required: list[str], **properties: Any) -> dict[str, Any]:
    return {"type": "object", "required": required, "properties": properties}


def _id(description: str) -> dict[str, Any]:
    return {"type": "string", "minLength": 1, "description": description}


def _nullable_id(description: str) -> dict[str, Any]:
    return {"type": ["string", "null"], "minLength": 1, "description": description}


def _link() -> dict[str, Any]:
    return {"type": "string", "pattern": "^/v1/", "description": "a path of this API"}


def _common_defs() -> dict[str, Any]:
    return {
        "pose": {
            "description": "env_from_object: 4×4 row-major, metres; maps object-model "
            "coordinates into the environment frame",
            "type": "array",
            "minItems": 4,
            "maxItems": 4,
            "items": {
                "type": "array",
                "minItems": 4,
                "maxItems": 4,
                "items": {"type": "number"},
            },
        },
        "error": _obj(
            ["code", "detail"],
            code={"type": ["string", "null"], "description": "machine-readable error code"},
            detail={"type": ["string", "null"], "description": "what a person can act on"},
        ),
        "change": _obj(
            ["id", "type", "object", "instance_id", "pose"],
            id=_id("the change"),
            type={"enum": [c.value for c in ChangeType]},
            object={"type": ["string", "null"], "description": "the object's class name"},
            instance_id=_nullable_id("the twin instance the change concerns"),
            external_id=_nullable_id(
                "the twin platform's id of that instance (seeded or corrected), when it has one"
            ),
            pose={"anyOf": [{"$ref": "#/$defs/pose"}, {"type": "null"}]},
            previous_pose={
                "anyOf": [{"$ref": "#/$defs/pose"}, {"type": "null"}],
                "description": "set for moved and removed",
            },
            replaced_object={
                "type": ["string", "null"],
                "description": "set for swapped: the class it replaced",
            },
            pose_quality={
                "type": ["object", "null"],
                "description": "fitness, inlier_rmse, cluster_coverage, runner_up_ratio, "
                "rotation_slack_deg, final_turn_deg, visible_fitness, chosen_by, verified, "
                "reasons, ambiguous, equivalent_poses",
            },
        ),
    }


def _data_defs() -> dict[str, Any]:
    job = _obj(
        ["job", "kind", "state", "error", "snapshot", "comparison", "object"],
        job=_id("the job"),
        kind={"enum": [k.value for k in JobKind]},
        state={"enum": [JobState.failed.value, JobState.cancelled.value]},
        error={"$ref": "#/$defs/error"},
        snapshot=_nullable_id("the job's snapshot, which ends with it"),
        comparison=_nullable_id("the job's comparison, which ends with it"),
        object=_nullable_id("the job's library object, which ends with it"),
    )
    return {
        EventType.snapshot_reconstructed.value: _obj(
            ["snapshot", "environment", "seq", "quality", "links"],
            snapshot=_id("the snapshot"),
            environment=_id("its environment"),
            seq={"type": "integer", "minimum": 1},
            quality={"type": ["object", "null"], "description": "reconstruction figures"},
            links=_obj(["pointcloud"], pointcloud=_link()),
        ),
        EventType.comparison_completed.value: _obj(
            ["comparison", "environment", "before", "after", "changes", "links"],
            comparison=_id("the comparison"),
            environment=_id("its environment"),
            before=_id("the earlier snapshot"),
            after=_id("the later snapshot"),
            changes={"type": "array", "items": {"$ref": "#/$defs/change"}},
            links=_obj(["comparison"], comparison=_link()),
        ),
        EventType.twin_updated.value: _obj(
            ["environment", "snapshot", "seq", "outcome", "comparison", "links"],
            environment=_id("the environment"),
            snapshot=_id("the snapshot the twin took into account"),
            seq={"type": "integer", "minimum": 1},
            outcome={"enum": [u.value for u in TwinUpdate]},
            comparison=_nullable_id("the comparison applied (outcome applied)"),
            reason=_obj(
                ["state"],
                state={"type": "string", "description": "the skipped snapshot's state"},
                code={"type": ["string", "null"]},
                detail={"type": ["string", "null"]},
            ),
            links=_obj(["state", "snapshot"], state=_link(), snapshot=_link(), comparison=_link()),
            instances={
                "type": "array",
                "description": "outcome applied: each instance the comparison's changes "
                "touched, in the order the twin applied them",
                "items": _obj(
                    ["instance_id", "external_id", "change_type", "present"],
                    instance_id=_id("the twin instance"),
                    external_id=_nullable_id("the twin platform's id of it, when it has one"),
                    change_type={"enum": [c.value for c in ChangeType]},
                    present={"type": "boolean", "description": "false once it was removed"},
                ),
            },
        ),
        EventType.twin_blocked.value: _obj(
            ["environment", "snapshot", "seq", "comparison", "twin_seq", "error", "links"],
            environment=_id("the environment"),
            snapshot=_id("the snapshot whose automatic comparison failed"),
            seq={"type": "integer", "minimum": 1},
            comparison=_id("the failed comparison"),
            twin_seq={"type": "integer", "minimum": 0},
            error={"$ref": "#/$defs/error"},
            links=_obj(["comparison", "retry"], comparison=_link(), retry=_link()),
        ),
        EventType.job_failed.value: job,
        EventType.job_cancelled.value: job,
    }


def _cloudevent() -> dict[str, Any]:
    by_type = [
        {
            "if": {"properties": {"type": {"const": t.value}}},
            "then": {
                "properties": {
                    "data": {"$ref": f"#/$defs/{t.value}"},
                    "dataschema": {"const": dataschema(t.value)},
                }
            },
        }
        for t in EventType
    ]
    return {
        "type": "object",
        "required": ["specversion", "id", "source", "type", "time", "datacontenttype", "data"],
        "properties": {
            "specversion": {"const": "1.0"},
            "id": _id("the event; webhook-id of its delivery"),
            "source": {"type": "string", "pattern": "^/twindelta(/environments/[^/]+)?$"},
            "type": {"enum": [t.value for t in EventType]},
            "subject": {"type": "string", "minLength": 1},
            "time": {"type": "string", "format": "date-time"},
            "datacontenttype": {"const": "application/json"},
            "dataschema": {"type": "string", "format": "uri"},
            "data": {"type": "object"},
        },
        "allOf": by_type,
    }


def event_schema() -> dict[str, Any]:
    """The whole schema: a CloudEvent (structured mode) of any type, with ``$defs``."""
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "$id": EVENTS_SCHEMA_ID,
        "title": "twindelta webhook events",
        "description": "A CloudEvents 1.0 structured body as a cloudevents webhook "
        "subscription receives it; $defs/<event type> is that type's data.",
        **_cloudevent(),
        "$defs": {**_common_defs(), **_data_defs()},
    }


def schema_text() -> str:
    """:func:`event_schema` as ``openapi/events.schema.json`` holds it."""
    return json.dumps(event_schema(), indent=2, ensure_ascii=False) + "\n"


if __name__ == "__main__":  # python -m app.core.eventschema > openapi/events.schema.json
    sys.stdout.write(schema_text())
