"""Platform adapters: a twin change as the body a twin platform's own update API takes, one
body per changed instance of a ``twin.updated`` event whose comparison was applied.

- ``azure-digital-twins``: a JSON Patch (RFC 6902, ``application/json-patch+json``) that
  Azure Digital Twins' *Update DigitalTwin* (``PATCH /digitaltwins/{id}``) accepts, on a twin
  of the DTDL v3 interface :data:`ADT_MODEL_ID` (``docs/adt/TwinInstance.json``). Every
  operation is ``add``, which sets a property whether or not the twin has it yet, so the
  same patch applies to an existing twin and, applied to an empty one, gives the complete
  twin a receiver creates (ADT cannot create a twin by PATCH).
- ``eclipse-ditto``: a JSON merge patch (RFC 7396, ``application/merge-patch+json``) of a
  Ditto thing (``thingId`` ``twindelta:<twin id>``, ``attributes``, ``features.pose``),
  as ``PATCH /api/2/things/{thingId}`` takes it (Ditto 3.3+ creates a missing thing from it).

The platform's twin is addressed by the instance's ``external_id`` (the platform's own id,
set by seeding or a correction) when it has one, else by twindelta's instance id (fixed
when the delivery is made: ``Delivery.twin_id``); the Ditto patch then also sets
``attributes.externalId`` (the ADT twin's own id is the external id, so the DTDL interface is
unchanged).

A removed instance (``removed``, or the replaced one of ``swapped``) keeps its twin or thing
with ``present: false``; its pose is left alone in ADT and the ``pose`` feature is deleted
(``null``) in Ditto. Poses are ``env_from_object``: 4×4, metres, row-major.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime
from enum import StrEnum
from typing import Any
from urllib.parse import quote

from sqlalchemy.orm import Session

from app.core.enums import EventType, TwinUpdate
from app.core.models import Event, InstancePose, TwinInstance
from app.core.twin_records import changed_instances
from app.core.webhooks.payload import aware

log = logging.getLogger(__name__)

ADT_MODEL_ID = "dtmi:twindelta:TwinInstance;1"
DITTO_NAMESPACE = "twindelta"


class WebhookFormat(StrEnum):
    """The body a subscription receives."""

    cloudevents = "cloudevents"
    azure_digital_twins = "azure-digital-twins"
    eclipse_ditto = "eclipse-ditto"


CONTENT_TYPES = {
    WebhookFormat.cloudevents: "application/cloudevents+json; charset=utf-8",
    WebhookFormat.azure_digital_twins: "application/json-patch+json",
    WebhookFormat.eclipse_ditto: "application/merge-patch+json",
}
# the event types an adapter subscription can receive: the twin's own changes
ADAPTER_EVENT_TYPES = frozenset({EventType.twin_updated})


@dataclass(frozen=True)
class InstanceChange:
    """One twin instance as a ``twin.updated`` event left it.

    ``pose`` is ``env_from_object`` (4×4, metres) or None for a removal; ``present`` is
    False once the instance was removed (or replaced by a swap) at ``snapshot``."""

    instance_id: str
    environment_id: str
    object_class: str
    library_object_id: str | None
    change_type: str  # added | removed | moved | swapped (the comparison's change)
    present: bool
    pose: list[list[float]] | None
    pose_verified: bool | None
    snapshot_id: str
    seq: int
    comparison_id: str
    changed_at: datetime
    external_id: str | None = None  # the twin platform's id, when the instance has one

    @property
    def twin_id(self) -> str:
        """The platform's id of the twin: the external id, else the instance id."""
        return self.external_id or self.instance_id


def instance_changes(session: Session, event: Event) -> list[InstanceChange]:
    """The instances a ``twin.updated`` event with outcome ``applied`` changed, in the order
    the twin applied them; empty for any other event. Reads the instance records the
    comparison wrote in the same transaction."""
    data = event.data if isinstance(event.data, dict) else {}
    if event.type != EventType.twin_updated or data.get("outcome") != TwinUpdate.applied:
        return []
    snapshot_id, comparison_id = data.get("snapshot"), data.get("comparison")
    if not snapshot_id or not comparison_id:
        return []
    return [
        _change(record, instance, event, str(snapshot_id), int(data.get("seq") or 0))
        for record, instance in changed_instances(session, snapshot_id, comparison_id)
    ]


def _change(
    record: InstancePose, instance: TwinInstance, event: Event, snapshot_id: str, seq: int
) -> InstanceChange:
    present = instance.closed_snapshot_id != snapshot_id
    quality = instance.pose_quality if present and isinstance(instance.pose_quality, dict) else {}
    verified = quality.get("verified")
    return InstanceChange(
        instance_id=instance.id,
        external_id=instance.external_id,
        environment_id=instance.environment_id,
        object_class=instance.object_name,
        library_object_id=instance.object_id,
        change_type=str(record.change_type),
        present=present,
        pose=record.pose if present else None,
        pose_verified=verified if isinstance(verified, bool) else None,
        snapshot_id=snapshot_id,
        seq=seq,
        comparison_id=str(record.comparison_id),
        changed_at=event.created_at,
    )


def pose_value(pose: Sequence[Sequence[float]] | None) -> dict[str, Any] | None:
    """``env_from_object`` (4×4, metres) as the adapters carry it: ``matrix`` (16 numbers,
    row-major) and ``position`` (its translation, metres); None when it is not a 4×4."""
    if pose is None or len(pose) != 4 or any(len(row) != 4 for row in pose):
        if pose is not None:
            log.warning("pose %r is not 4×4; the adapter body leaves it out", pose)
        return None
    matrix = [float(v) for row in pose for v in row]
    return {"matrix": matrix, "position": {"x": matrix[3], "y": matrix[7], "z": matrix[11]}}


def _time(value: datetime) -> str:
    return aware(value).isoformat().replace("+00:00", "Z")


def _twin_properties(change: InstanceChange) -> dict[str, Any]:
    """The properties both adapters set on the platform's twin (ADT properties, Ditto
    attributes): class, environment, presence, the change and when it happened."""
    props: dict[str, Any] = {
        "objectClass": change.object_class,
        "environment": change.environment_id,
        "present": change.present,
        "changeType": change.change_type,
        "snapshot": change.snapshot_id,
        "seq": change.seq,
        "comparison": change.comparison_id,
        "changedAt": _time(change.changed_at),
    }
    if change.library_object_id is not None:
        props["libraryObject"] = change.library_object_id
    return props


def adt_patch(change: InstanceChange) -> list[dict[str, Any]]:
    """The JSON Patch (RFC 6902) for Azure Digital Twins' Update DigitalTwin on twin
    ``change.twin_id`` of model :data:`ADT_MODEL_ID`: ``add`` operations only (valid
    whether the property is set yet or not). A removal sets ``present`` false and leaves
    the last pose."""
    values = _twin_properties(change)
    pose = pose_value(change.pose)
    if pose is not None:
        values["pose"] = pose
    if change.pose_verified is not None:
        values["poseVerified"] = change.pose_verified
    return [{"op": "add", "path": f"/{name}", "value": value} for name, value in values.items()]


def ditto_thing_id(twin_id: str) -> str:
    """The Ditto thing id of a twin id (:attr:`InstanceChange.twin_id`): ``namespace:name``,
    the name the twin id percent-encoded (RFC 3986, UTF-8) but for unreserved characters
    and ``!&'()*+,;=:@$`` (a leading ``$`` too), so that it meets Ditto's name rules (no
    ``/``, no control or non-ASCII characters) and reads the same in a URL path; an
    instance id is unchanged."""
    name = quote(twin_id, safe="!&'()*+,;=:@-._~$")
    if name.startswith("$"):
        name = "%24" + name[1:]
    return f"{DITTO_NAMESPACE}:{name}"


def ditto_merge_patch(change: InstanceChange) -> dict[str, Any]:
    """The JSON merge patch (RFC 7396) of thing :func:`ditto_thing_id` for Ditto's
    ``PATCH /api/2/things/{thingId}``. A removal sets ``attributes.present`` false and
    deletes the ``pose`` feature (``null``)."""
    attributes = _twin_properties(change)
    if change.external_id is not None:
        attributes["externalId"] = change.external_id
    pose = pose_value(change.pose)
    feature: dict[str, Any] | None = None
    if pose is not None:
        matrix = pose["matrix"]
        properties: dict[str, Any] = {
            "envFromObject": [matrix[i : i + 4] for i in range(0, 16, 4)],
            "position": pose["position"],
        }
        if change.pose_verified is not None:
            properties["verified"] = change.pose_verified
        feature = {"properties": properties}
    patch: dict[str, Any] = {
        "thingId": ditto_thing_id(change.twin_id),
        "attributes": attributes,
    }
    if feature is not None or not change.present:
        patch["features"] = {"pose": feature}
    return patch


def render(fmt: WebhookFormat, change: InstanceChange) -> Any:
    """The adapter body of ``change`` for ``fmt`` (not for CloudEvents: one body per event)."""
    if fmt == WebhookFormat.azure_digital_twins:
        return adt_patch(change)
    if fmt == WebhookFormat.eclipse_ditto:
        return ditto_merge_patch(change)
    raise ValueError(f"format {fmt} has no per-instance body")


def target_headers(
    fmt: WebhookFormat, event: Event, instance_id: str, twin_id: str | None = None
) -> dict[str, str]:
    """The headers that say what an adapter body is about: the platform's id of the twin
    (:attr:`InstanceChange.twin_id`, the instance id when None: ``twindelta-twin-id`` for
    ADT, ``twindelta-thing-id`` its :func:`ditto_thing_id` for Ditto) and the CloudEvents
    HTTP binary-mode attributes (``ce-*``; the body is the event's data)."""
    source = f"/twindelta/environments/{event.environment_id}"
    headers = {
        "ce-specversion": "1.0",
        "ce-id": message_id(event.id, instance_id),
        "ce-source": source,
        "ce-type": str(event.type),
        "ce-subject": f"objects/{instance_id}",
        "ce-time": _time(event.created_at),
    }
    if fmt == WebhookFormat.azure_digital_twins:
        headers["twindelta-twin-id"] = twin_id or instance_id
    elif fmt == WebhookFormat.eclipse_ditto:
        headers["twindelta-thing-id"] = ditto_thing_id(twin_id or instance_id)
    return headers


def message_id(event_id: str, instance_id: str | None) -> str:
    """``webhook-id`` of a delivery: the event id, and for an adapter body the event and
    instance (each instance's patch is its own message); the same on every retry."""
    return event_id if instance_id is None else f"{event_id}:{instance_id}"
