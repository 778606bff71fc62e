"""Hostile input over HTTP: values that parse as JSON (or almost) but break naive conversions
(unicode digits, 5,000-digit numbers, 10^400, NaN, Infinity, 1e400, nesting 200,000 deep,
nulls and strings where numbers belong) are each a 422 naming the field, never a 500, and
nothing is stored."""

from __future__ import annotations

import io
import json
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from sqlalchemy.exc import DataError

from app.core.errors import InvalidInput
from app.core.options import check_stage_options
from app.main import create_app
from tests.app.api.test_objects_api import PLY_CUBE
from tests.app.api.test_snapshots_upload import as_parts, capture, make_env, upload
from tests.app.conftest import Keys, SentTasks

EYE = np.eye(4).tolist()
HUGE = "1" + "0" * 5000  # past Python's 4,300-digit int-string limit
DEEP = "[" * 200_000


def post_env(client: TestClient, keys: Keys, raw: str) -> Any:
    return client.post(
        "/v1/environments",
        content=raw.encode(),
        headers={**keys.headers(), "Content-Type": "application/json"},
    )


def env_body(**fields: str) -> str:
    """An environment body with ``fields`` spliced in as raw JSON text."""
    parts = ['"name": "line-1"', '"classes": ["a"]'] + [f'"{k}": {v}' for k, v in fields.items()]
    return "{" + ", ".join(parts) + "}"


def markers(poses: str) -> str:
    return '{"markers": {"size": 0.1, "poses": ' + poses + "}}"


@pytest.mark.parametrize(
    ("raw", "field"),
    [
        (env_body(reference=markers('{"²": ' + json.dumps(EYE) + "}")), "reference.markers.poses"),
        (env_body(reference=markers('{"' + "9" * 5000 + '": ' + json.dumps(EYE) + "}")),
         "reference.markers.poses"),
        (env_body(reference=markers('{"50": ' + json.dumps(EYE) + "}")),
         "reference.markers.poses"),
        (env_body(reference=markers('{"1": ' + json.dumps(EYE) + ', "01": '
                                    + json.dumps(EYE) + "}")), "reference.markers.poses"),
        (env_body(options='{"compare": {"max_clusters": 1' + "0" * 400 + "}}"),
         "options.compare.max_clusters"),
        (env_body(options='{"compare": {"max_clusters": ' + HUGE + "}}"),
         "options.compare.max_clusters"),
        (env_body(options='{"compare": {"identify_threshold": 1' + "0" * 400 + "}}"),
         "options.compare.identify_threshold"),
        (env_body(options='{"compare": {"identify_threshold": NaN}}'),
         "options.compare.identify_threshold"),
        (env_body(options='{"compare": {"identify_threshold": -Infinity}}'),
         "options.compare.identify_threshold"),
        (env_body(options='{"compare": {"identify_threshold": 1e400}}'),
         "options.compare.identify_threshold"),
        (env_body(options='{"reconstruct": {"icp_max_distances_m": [0.1, 1e400]}}'),
         "options.reconstruct.icp_max_distances_m[1]"),
        (env_body(options='{"compare": {"threshold": {"kind": "fixed", "distance": NaN}}}'),
         "options.compare.threshold.distance"),
        (env_body(reference=markers('{"0": [[1, 0, 0, ' + HUGE + "]]}")),
         "reference.markers.poses"),
        (env_body(reference='{"markers": {"size": NaN, "poses": {}}}'), "reference.markers.size"),
        (env_body(options='{"compare": ' + "[" * 100 + "]" * 100 + "}"),
         "nested more than"),
        (DEEP, "nested more than"),
        (env_body(options=DEEP), "nested more than"),
    ],
    ids=[
        "unicode-digit-marker", "5000-digit-marker", "marker-past-dictionary",
        "same-marker-twice", "int-10^400", "int-5000-digits", "float-option-10^400",
        "nan", "infinity", "1e400", "float-list-1e400", "threshold-nan", "pose-5000-digits",
        "marker-size-nan", "nested-100", "bare-200000-brackets", "nested-200000",
    ],
)  # fmt: skip
def test_environment_hostile_json_is_a_422_naming_the_field(
    client: TestClient, keys: Keys, raw: str, field: str
) -> None:
    r = post_env(client, keys, raw)
    assert r.status_code == 422, r.text
    assert r.json()["error"] == "InvalidInput" and field in r.json()["detail"], r.text
    assert len(r.text) < 2000, "the answer must not echo a huge value back"
    assert client.get("/v1/environments", headers=keys.headers("read")).json() == []


def test_unicode_and_padded_marker_ids_are_named_in_the_detail(
    client: TestClient, keys: Keys
) -> None:
    r = post_env(client, keys, env_body(reference=markers('{"²": ' + json.dumps(EYE) + "}")))
    assert r.status_code == 422 and "'²' is not an integer" in r.json()["detail"], r.text
    good = env_body(reference=markers('{"007": ' + json.dumps(EYE) + "}"))
    r = post_env(client, keys, good)
    assert r.status_code == 201, r.text
    assert list(r.json()["reference"]["markers"]["poses"]) == ["7"]


def test_options_checker_rejects_out_of_range_numbers_directly() -> None:
    """The option checker is also called by the core (comparisons), not only behind the
    JSON guard: 10^400 and a non-finite float are InvalidInput there too."""
    for options, field in [
        ({"max_clusters": 10**400}, "options.max_clusters"),
        ({"identify_threshold": 10**400}, "options.identify_threshold"),
        ({"identify_threshold": float("nan")}, "options.identify_threshold"),
        ({"threshold": {"kind": "fixed", "distance": float("inf")}}, "options.threshold.distance"),
        ({"max_clusters": 2**63}, "options.max_clusters"),
    ]:
        with pytest.raises(InvalidInput, match=field.replace(".", r"\.")):
            check_stage_options("compare", options)
    assert check_stage_options("compare", {"max_clusters": 12, "identify_threshold": 1}) == {
        "max_clusters": 12,
        "identify_threshold": 1,
    }


@pytest.mark.parametrize(
    ("symmetry", "field"),
    [
        ('{"kind": "continuous", "axis": ["a", 0, 0]}', "symmetry.axis"),
        ('{"kind": "continuous", "axis": [null, 0, 0]}', "symmetry.axis"),
        ('{"kind": "continuous", "axis": [1e400, 0, 0]}', "symmetry.axis"),
        ('{"kind": "continuous", "axis": [NaN, 0, 1]}', "symmetry.axis"),
        ('{"kind": "continuous", "axis": [' + HUGE + ", 0, 0]}", "symmetry.axis"),
        ('{"kind": "continuous", "axis": [0, 0, 1], "origin": [0, "x", 0]}', "symmetry.origin"),
        ('{"kind": "continuous", "axis": [true, 0, 0]}', "symmetry.axis"),
        ('{"kind": "discrete", "rotations": [[1, 2]]}', "symmetry.rotations[0]"),
        ('{"kind": "discrete", "rotations": [' + json.dumps((2 * np.eye(4)).tolist()) + "]}",
         "symmetry.rotations[0]"),
        ('{"kind": "discrete", "rotations": []}', "symmetry.rotations"),
        ('{"kind": "none", "appearance_breaks": "yes"}', "symmetry.appearance_breaks"),
        ('{"kind": "continuous", "axis": [0, 0, 1], "axes": [1, 0, 0]}', "symmetry"),
        (DEEP, "symmetry"),
        ('{"kind": "discrete", "rotations": ' + "[" * 100 + "]" * 100 + "}", "nested more than"),
    ],
    ids=[
        "string-axis", "null-axis", "inf-axis", "nan-axis", "5000-digit-axis", "string-origin",
        "bool-axis", "rotation-shape", "rotation-scaled", "no-rotations", "breaks-not-bool",
        "unknown-key", "200000-brackets", "nested-100",
    ],
)  # fmt: skip
def test_object_symmetry_hostile_spec_is_a_422(
    client: TestClient, keys: Keys, sent_tasks: SentTasks, symmetry: str, field: str
) -> None:
    r = client.post(
        "/v1/objects",
        files={"file": ("bracket.ply", io.BytesIO(PLY_CUBE))},
        data={"name": "bracket", "symmetry": symmetry},
        headers=keys.headers(),
    )
    assert r.status_code == 422, r.text
    assert r.json()["error"] == "InvalidInput" and field in r.json()["detail"], r.text
    assert len(r.text) < 2000
    assert sent_tasks.names() == []


def test_object_symmetry_good_specs_are_kept(
    client: TestClient, keys: Keys, sent_tasks: SentTasks
) -> None:
    quarter = [[0, -1, 0, 0], [1, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    for name, spec in [
        ("a", {"kind": "continuous", "axis": [0, 0, 2], "origin": [0.1, 0, 0]}),
        ("b", {"kind": "discrete", "rotations": [quarter], "appearance_breaks": True}),
    ]:
        r = client.post(
            "/v1/objects",
            files={"file": ("bracket.ply", io.BytesIO(PLY_CUBE))},
            data={"name": name, "symmetry": json.dumps(spec)},
            headers=keys.headers(),
        )
        assert r.status_code == 202, r.text
        assert r.json()["symmetry_requested"] == spec


CAMERA = '{"model": "PINHOLE", "width": 32, "height": 24, "params": [30, 30, 16, 12]}'


@pytest.mark.parametrize(
    ("cameras", "detail"),
    [
        (DEEP, "nested more than"),
        ('{"intrinsics": ' + "[" * 50_000 + "]" * 50_000 + "}", "nested more than"),
        ('{"intrinsics": {"model": "PINHOLE", "width": ' + HUGE
         + ', "height": 24, "params": [30, 30, 16, 12]}}', "intrinsics.width"),
        ('{"intrinsics": {"model": "PINHOLE", "width": 1' + "0" * 30
         + ', "height": 24, "params": [30, 30, 16, 12]}}', "width"),
        ('{"intrinsics": {"model": "PINHOLE", "width": 32, "height": 24, '
         '"params": [30, NaN, 16, 12]}}', "params"),
        ('{"intrinsics": ' + CAMERA + ', "poses": {"a0.jpg": [[1, 0, 0, 1e400], [0, 1, 0, 0], '
         "[0, 0, 1, 0], [0, 0, 0, 1]]}}", "poses"),
        ('{"intrinsics": ' + CAMERA + ', "poses": {"a0.jpg": [["a", 0, 0, 0], [0, 1, 0, 0], '
         "[0, 0, 1, 0], [0, 0, 0, 1]]}}", "poses"),
        ('{"intrinsics": ' + CAMERA + ', "poses": {"a0.jpg": [[null, 0, 0, 0], [0, 1, 0, 0], '
         "[0, 0, 1, 0], [0, 0, 0, 1]]}}", "poses"),
    ],
    ids=[
        "200000-brackets", "nested-50000", "5000-digit-width", "width-10^30", "nan-param",
        "1e400-pose", "string-in-pose", "null-in-pose",
    ],
)  # fmt: skip
def test_cameras_json_hostile_document_is_a_422(
    client: TestClient, keys: Keys, sent_tasks: SentTasks, cameras: str, detail: str
) -> None:
    env_id = make_env(client, keys)
    files = capture()
    files["cameras.json"] = cameras.encode()
    r = upload(client, keys, env_id, as_parts(files))
    assert (r.status_code, r.json()["error"]) == (422, "InvalidCameras"), r.text
    assert "cameras.json" in r.json()["detail"] and detail in r.json()["detail"], r.text
    assert len(r.text) < 2000
    assert sent_tasks.names() == []


@pytest.mark.parametrize(
    ("raw", "field"),
    [
        ('{"name": "line\\u0000one", "classes": ["a"]}', "name: text with a NUL character"),
        ('{"name": "line-1", "classes": ["\\ud800"]}', "classes[0]: text with an unpaired"),
        (env_body(options='{"compare": {"a\\u0000": 1}}'), "the key is text with a NUL"),
    ],
    ids=["nul-in-name", "lone-surrogate", "nul-in-key"],
)
def test_text_no_database_stores_is_a_422(
    client: TestClient, keys: Keys, raw: str, field: str
) -> None:
    """Found by schemathesis: a NUL in a name was a 500 on PostgreSQL (DataError)."""
    r = post_env(client, keys, raw)
    assert r.status_code == 422 and field in r.json()["detail"], r.text
    assert client.get("/v1/environments", headers=keys.headers("read")).json() == []


def test_nul_in_a_path_or_query_is_a_422(client: TestClient, keys: Keys) -> None:
    for url in ("/v1/environments/a%00b", "/v1/jobs/%00", "/v1/webhooks/x/deliveries?state=%00"):
        r = client.get(url, headers=keys.headers())
        assert r.status_code == 422 and "NUL" in r.json()["detail"], (url, r.text)


def test_a_name_with_a_nul_is_a_422_on_every_database(
    client: TestClient, keys: Keys, sent_tasks: SentTasks
) -> None:
    """A form field no JSON guard sees: PostgreSQL would refuse the NUL, SQLite would store
    it; the API refuses it first, naming the field, on both."""
    r = client.post(
        "/v1/objects",
        files={"file": ("bracket.ply", io.BytesIO(PLY_CUBE))},
        data={"name": "brack\x00et"},
        headers=keys.headers(),
    )
    assert r.status_code == 422, r.text
    assert r.json()["error"] == "InvalidInput" and r.json()["detail"].startswith("name: ")
    assert sent_tasks.names() == []


def test_a_value_the_database_refuses_is_a_422_not_a_500() -> None:
    """The safety net past the API's own checks: a DataError from the database driver is the
    request's fault, rendered as a 422 with the database's first line, never a 500."""
    app = create_app()

    def refused() -> None:
        raise DataError("INSERT ...", {}, Exception("invalid byte sequence 0x00\nCONTEXT ..."))

    app.add_api_route("/v1/refused", refused, methods=["GET"])
    r = TestClient(app, raise_server_exceptions=False).get("/v1/refused")
    assert r.status_code == 422, r.text
    assert r.json() == {
        "error": "InvalidInput",
        "detail": "a value the database cannot store: invalid byte sequence 0x00",
    }
