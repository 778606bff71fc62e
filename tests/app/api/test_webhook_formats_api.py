"""The webhook ``format`` over HTTP: the default, the read schema, unknown formats and event
types an adapter cannot carry refused with 422 naming them, nothing stored on refusal."""

from __future__ import annotations

from typing import Any

import pytest
from fastapi.testclient import TestClient

from tests.app.conftest import Keys

PUBLIC = "https://93.184.216.34/hooks/twin"


def post(client: TestClient, keys: Keys, **body: Any) -> Any:
    return client.post("/v1/webhooks", json={"url": PUBLIC, **body}, headers=keys.headers())


def test_format_defaults_to_cloudevents_and_is_read_back(client: TestClient, keys: Keys) -> None:
    plain = post(client, keys)
    assert plain.status_code == 201 and plain.json()["format"] == "cloudevents"
    assert len(plain.json()["event_types"]) == 6  # every type, as before
    for fmt in ("azure-digital-twins", "eclipse-ditto"):
        made = post(client, keys, format=fmt)
        assert made.status_code == 201, made.text
        assert made.json()["format"] == fmt and made.json()["event_types"] == ["twin.updated"]
        got = client.get(f"/v1/webhooks/{made.json()['id']}", headers=keys.headers()).json()
        assert got["format"] == fmt
    listed = client.get("/v1/webhooks", headers=keys.headers()).json()
    assert sorted(w["format"] for w in listed) == [
        "azure-digital-twins",
        "cloudevents",
        "eclipse-ditto",
    ]


@pytest.mark.parametrize(
    ("body", "named"),
    [
        ({"format": "azure"}, "unknown format 'azure'"),
        ({"format": "CloudEvents"}, "unknown format 'CloudEvents'"),
        ({"format": 3}, "format"),
        (
            {"format": "eclipse-ditto", "event_types": ["twin.updated", "job.failed"]},
            "not job.failed",
        ),
        ({"format": "azure-digital-twins", "event_types": ["comparison.completed"]}, "sends only"),
    ],
)
def test_bad_formats_are_refused_naming_them(
    client: TestClient, keys: Keys, body: dict[str, Any], named: str
) -> None:
    r = post(client, keys, **body)
    assert r.status_code == 422 and r.json()["error"] == "InvalidInput", r.text
    assert named in r.json()["detail"]
    assert client.get("/v1/webhooks", headers=keys.headers()).json() == []
