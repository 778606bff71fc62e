"""A JSON Schema of an Eclipse Ditto thing (API 2), for checking the things the
``eclipse-ditto`` merge patches produce.

Written for these tests after Ditto's published thing model (its documentation's
``thing_v2.json`` schema: ``thingId`` and ``policyId`` required, ``attributes`` any object,
``features`` an object of features each with ``definition`` and ``properties``) and Ditto's
entity id rules (``RegexPatterns``: a namespace in Java package notation, ``:``, a name
without control characters or ``/``). It is stricter than the published schema where Ditto
itself is (unknown top-level members, feature ids and attribute names with ``/``), so a
misspelt member fails here as it would fail in Ditto."""

from __future__ import annotations

from typing import Any

NAMESPACE = r"(?:[a-zA-Z]\w*(?:[.\-][a-zA-Z]\w*)*)?"
NAME = r"(?:[^\x00-\x1F\x7F-\xFF/$]|%[0-9a-fA-F]{2})(?:[^\x00-\x1F\x7F-\xFF/]|%[0-9a-fA-F]{2})*"
ENTITY_ID = f"^{NAMESPACE}:{NAME}$"
DEFINITION = r"^[_a-zA-Z0-9\-.]+:[_a-zA-Z0-9\-.]+:[_a-zA-Z0-9\-.]+$"
KEY = {"type": "string", "pattern": "^[^/]+$"}

THING_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "Ditto thing (API 2)",
    "type": "object",
    "required": ["thingId", "policyId"],
    "additionalProperties": False,
    "properties": {
        "thingId": {"type": "string", "pattern": ENTITY_ID},
        "policyId": {"type": "string", "pattern": ENTITY_ID},
        "definition": {"type": "string", "pattern": DEFINITION},
        "attributes": {"type": "object", "propertyNames": KEY},
        "features": {
            "type": "object",
            "propertyNames": KEY,
            "additionalProperties": {
                "type": "object",
                "additionalProperties": False,
                "properties": {
                    "definition": {
                        "type": "array",
                        "minItems": 1,
                        "uniqueItems": True,
                        "items": {"type": "string", "pattern": DEFINITION},
                    },
                    "properties": {"type": "object", "propertyNames": KEY},
                    "desiredProperties": {"type": "object", "propertyNames": KEY},
                },
            },
        },
        "_namespace": {"type": "string"},
        "_revision": {"type": "integer"},
        "_created": {"type": "string"},
        "_modified": {"type": "string"},
    },
}
