"""The object library over HTTP: a good upload queues preparation; every bad input is a 422
(or 409 / 413) naming the problem and leaves nothing stored."""

from __future__ import annotations

import io
import struct
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from app.core.objects import format_problem
from tests.app.conftest import Keys, SentTasks

PLY_CUBE = b"""ply
format ascii 1.0
element vertex 3
property float x
property float y
property float z
element face 1
property list uchar int vertex_indices
end_header
0 0 0
1 0 0
0 1 0
3 0 1 2
"""


def upload(
    client: TestClient, keys: Keys, filename: str, content: bytes, **form: str
) -> tuple[int, dict[str, object]]:
    r = client.post(
        "/v1/objects",
        files={"file": (filename, io.BytesIO(content))},
        data={"name": "bracket", **form},
        headers=keys.headers(),
    )
    return r.status_code, r.json()


def test_good_upload_queues_preparation(
    client: TestClient, keys: Keys, sent_tasks: SentTasks, data_dir: Path
) -> None:
    status, body = upload(client, keys, "bracket.ply", PLY_CUBE, units="mm")
    assert status == 202, body
    assert body["name"] == "bracket" and body["state"] == "processing"
    assert sent_tasks.names() == ["object.prepare"]
    stored = [p for p in data_dir.rglob("objects/*/*") if p.is_file()]
    assert [p.read_bytes() for p in stored] == [PLY_CUBE]
    listed = client.get("/v1/objects", headers=keys.headers("read")).json()
    assert [o["id"] for o in listed] == [body["id"]]
    status, again = upload(client, keys, "bracket.ply", PLY_CUBE)
    assert status == 409 and again["error"] == "ObjectExists"


@pytest.mark.parametrize(
    ("filename", "content", "form", "message"),
    [
        ("bracket.ply", b"", {}, "is empty"),
        ("bracket.fbx", PLY_CUBE, {}, "is not a model file"),
        ("bracket.ply", PLY_CUBE, {"units": "inch"}, "units"),
        ("bracket.ply", PLY_CUBE, {"symmetry": "{not json"}, "symmetry"),
        ("bracket.ply", PLY_CUBE, {"symmetry": '{"kind": "spiral"}'}, "symmetry"),
        ("bracket.ply", b"<html>not found</html>", {}, "starts with the line 'ply'"),
        ("bracket.glb", PLY_CUBE, {}, "glTF"),
        ("bracket.stl", b"\x00" * 100, {}, "STL"),
        ("bracket.obj", b"\x89PNG\r\n\x1a\n\x00\x00", {}, "vertex lines"),
        ("bracket.off", b"ply\n", {}, "OFF"),
        ("bracket.pcd", b"hello", {}, "FIELDS"),
    ],
)
def test_bad_input_is_a_422_naming_it_and_stores_nothing(
    client: TestClient,
    keys: Keys,
    sent_tasks: SentTasks,
    data_dir: Path,
    filename: str,
    content: bytes,
    form: dict[str, str],
    message: str,
) -> None:
    status, body = upload(client, keys, filename, content, **form)
    assert status == 422, body
    assert body["error"] == "InvalidInput" and message in str(body["detail"])
    assert client.get("/v1/objects", headers=keys.headers("read")).json() == []
    assert sent_tasks.names() == []
    stored = data_dir.rglob("objects/*/*")
    assert [p for p in stored if p.is_file()] == []


def test_format_signatures_accept_real_headers() -> None:
    binary_stl = b"\x00" * 80 + struct.pack("<I", 1) + b"\x00" * 50
    assert format_problem(".stl", binary_stl, len(binary_stl)) is None
    assert format_problem(".stl", b"solid cube\nendsolid\n", 20) is None
    assert format_problem(".off", b"# comment-free\nOFF\n3 1 0\n", 20) is not None
    assert format_problem(".off", b"COFF\n3 1 0\n", 11) is None
    assert format_problem(".obj", b"# exported\nmtllib a.mtl\nv 0 0 0\n", 30) is None
    assert format_problem(".pcd", b"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\n", 40) is None
    assert format_problem(".glb", b"glTF\x02\x00\x00\x00", 8) is None


def test_deleting_an_object_cancels_its_pending_preparation(
    client: TestClient, keys: Keys, sent_tasks: SentTasks
) -> None:
    status, body = upload(client, keys, "bracket.ply", PLY_CUBE)
    assert status == 202, body
    job_id = body["job"]["id"]  # type: ignore[index]
    r = client.delete(f"/v1/objects/{body['id']}", headers=keys.headers())
    assert r.status_code == 200, r.text
    job = client.get(f"/v1/jobs/{job_id}", headers=keys.headers("read")).json()
    assert job["state"] == "cancelled", job
    assert job["error"]["detail"] == "cancelled while queued"


@pytest.mark.parametrize("name", ["drill\x00", "\x00"])
def test_a_name_no_database_can_store_is_a_422(client: TestClient, keys: Keys, name: str) -> None:
    r = client.post(
        "/v1/objects",
        files={"file": ("bracket.ply", io.BytesIO(PLY_CUBE))},
        data={"name": name},
        headers=keys.headers(),
    )
    assert r.status_code == 422, r.text
    assert r.json()["detail"].startswith("name: text with")
