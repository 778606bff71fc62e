"""Laser scan upload over HTTP (POST /v1/environments/{id}/scans): each format accepted and
stored with its frame, idempotency, and every rejection (415 by content, 422 truncated /
empty / bad frame, 413 over the scan limit) naming the problem and leaving nothing behind."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select
from sqlalchemy.orm import Session, sessionmaker

from app.api.limits import body_limit
from app.core.models import Snapshot
from app.core.settings import get_settings
from tests.app.api.test_snapshots_upload import CLASSES, make_env, set_limits, stored_files
from tests.app.api.test_upload_limits import BOUNDARY, MB, drive, multipart_chunks
from tests.app.conftest import Keys, SentTasks
from tests.workers.pipeline.scan_scene import cloud, write_e57, write_las, write_ply

IDENTITY = {"transform": np.eye(4).tolist()}
SHEET = {"markers": {"size": 0.15, "poses": {"0": np.eye(4).tolist()}}}


def scan_bytes(tmp_path: Path, fmt: str, n: int = 200) -> bytes:
    """A small coloured scan of ``fmt`` (e57, las, laz, ply, ply_ascii) written by its library."""
    points, colors = cloud(n)
    path = tmp_path / f"scan.{fmt.removesuffix('_ascii')}"
    if fmt == "e57":
        write_e57(path, [(points, colors, np.eye(4))])
    elif fmt in ("las", "laz"):
        write_las(path, points, colors)
    else:
        write_ply(path, points, colors, ascii=fmt == "ply_ascii")
    return path.read_bytes()


def post_scan(
    client: TestClient,
    keys: Keys,
    env_id: str,
    body: bytes,
    frame: Any = IDENTITY,
    key: str | None = None,
    who: str = "capture",
) -> Any:
    headers = keys.headers(who)
    if key is not None:
        headers["Idempotency-Key"] = key
    data = (
        {} if frame is None else {"frame": frame if isinstance(frame, str) else json.dumps(frame)}
    )
    return client.post(
        f"/v1/environments/{env_id}/scans",
        files={"file": ("cloud.bin", body, "application/octet-stream")},
        data=data,
        headers=headers,
    )


@pytest.mark.parametrize("fmt", ["e57", "las", "laz", "ply", "ply_ascii"])
def test_each_format_is_stored_with_its_frame_and_queued(
    client: TestClient, keys: Keys, sent_tasks: SentTasks, data_dir: Path, tmp_path: Path, fmt: str
) -> None:
    env_id = make_env(client, keys)
    body = scan_bytes(tmp_path, fmt)
    frame = {
        "transform": [[0, -1, 0, 1.5], [1, 0, 0, 0], [0, 0, 1, 0.2], [0, 0, 0, 1]],
        "units": "mm",
    }
    r = post_scan(client, keys, env_id, body, frame)
    assert r.status_code == 202, r.text
    snap, job = r.json()["snapshot"], r.json()["job"]
    assert snap["source"] == "scan" and snap["seq"] == 1 and snap["state"] == "uploaded"
    assert snap["upload_bytes"] == len(body) and snap["n_images"] == 0
    assert r.headers["location"] == f"/v1/jobs/{job['id']}"
    assert sent_tasks.calls == [("snapshot.process", {"job_id": job["id"]})]
    stored_fmt = fmt.removesuffix("_ascii")
    prefix = f"snapshots/{snap['id']}"
    assert set(stored_files(data_dir)) == {
        f"{prefix}/scan/scan.{stored_fmt}",
        f"{prefix}/scan.json",
    }
    assert (data_dir / "files" / prefix / "scan" / f"scan.{stored_fmt}").read_bytes() == body
    record = json.loads((data_dir / "files" / prefix / "scan.json").read_text())
    assert record["format"] == stored_fmt and record["points_declared"] == 200
    assert record["frame"] == {
        "transform": [[float(v) for v in row] for row in frame["transform"]],
        "units": "mm",
    }  # type: ignore[union-attr]
    got = client.get(f"/v1/snapshots/{snap['id']}", headers=keys.headers("read")).json()
    assert got["source"] == "scan"


def test_photo_snapshots_say_their_source(client: TestClient, keys: Keys, session: Session) -> None:
    from tests.app.api.test_snapshots_upload import as_parts, capture, upload

    env_id = make_env(client, keys)
    r = upload(client, keys, env_id, as_parts(capture()))
    assert r.status_code == 202 and r.json()["snapshot"]["source"] == "photos"


def test_markers_frame_needs_the_environments_sheet(
    client: TestClient, keys: Keys, data_dir: Path, tmp_path: Path
) -> None:
    body = scan_bytes(tmp_path, "las")
    bare = make_env(client, keys, "bare")
    r = post_scan(client, keys, bare, body, {"markers": True})
    assert r.status_code == 422 and r.json()["error"] == "NoMarkerSheet", r.text
    assert stored_files(data_dir) == {}
    env = client.post(
        "/v1/environments",
        json={"name": "sheet", "classes": CLASSES, "reference": SHEET},
        headers=keys.headers(),
    ).json()["id"]
    r = post_scan(client, keys, env, body, {"markers": True})
    assert r.status_code == 202, r.text


def test_idempotency_key_replays_and_refuses_another_scan(
    client: TestClient, keys: Keys, session: Session, tmp_path: Path
) -> None:
    env_id = make_env(client, keys)
    body = scan_bytes(tmp_path, "ply")
    first = post_scan(client, keys, env_id, body, key="scan-1")
    again = post_scan(client, keys, env_id, body, key="scan-1")
    assert first.status_code == again.status_code == 202
    assert again.headers["idempotent-replayed"] == "true"
    assert again.json()["snapshot"]["id"] == first.json()["snapshot"]["id"]
    other_frame = post_scan(
        client, keys, env_id, body, {"markers": False, **IDENTITY, "units": "cm"}, key="scan-1"
    )
    assert other_frame.status_code == 409 and other_frame.json()["error"] == "IdempotencyKeyReused"
    count = session.scalar(
        select(func.count()).select_from(Snapshot).where(Snapshot.environment_id == env_id)
    )
    assert count == 1


def _truncated(tmp_path: Path, fmt: str) -> bytes:
    body = scan_bytes(tmp_path, fmt, n=2000)
    return body[: len(body) - 500]


def _empty(tmp_path: Path, fmt: str) -> bytes:
    path = tmp_path / f"empty.{fmt}"
    points, colors = np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    if fmt == "las":
        write_las(path, points, colors)
    else:
        path.write_bytes(
            b"ply\nformat binary_little_endian 1.0\nelement vertex 0\n"
            b"property float x\nproperty float y\nproperty float z\nend_header\n"
        )
    return path.read_bytes()


@pytest.mark.parametrize(
    ("make", "fmt", "code", "words"),
    [
        (_truncated, "las", "TruncatedScan", "declares 2000 points"),
        (_truncated, "laz", "TruncatedScan", "truncated"),
        (_truncated, "e57", "TruncatedScan", "truncated"),
        (_truncated, "ply", "TruncatedScan", "declares 2000 vertex elements"),
        (_empty, "las", "EmptyScan", "no points"),
        (_empty, "ply", "EmptyScan", "no points"),
    ],
)
def test_bad_files_are_422_naming_the_problem(
    client: TestClient, keys: Keys, session: Session, data_dir: Path, tmp_path: Path,
    make: Any, fmt: str, code: str, words: str,
) -> None:  # fmt: skip
    env_id = make_env(client, keys)
    r = post_scan(client, keys, env_id, make(tmp_path, fmt))
    assert r.status_code == 422, r.text
    assert r.json()["error"] == code and words in r.json()["detail"], r.json()
    assert "/tmp" not in r.json()["detail"]
    assert stored_files(data_dir) == {}
    assert session.scalar(select(func.count()).select_from(Snapshot)) == 0


@pytest.mark.parametrize(
    ("frame", "words"),
    [
        ({"transform": (np.eye(4) * 1.01).tolist()}, "last row"),
        ({"transform": [[1, 0, 0, 0], [0, 2, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}, "not a rotation"),
        (
            {"transform": [[-1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]},
            "not a rotation",
        ),
        ({"transform": np.eye(4)[:3].tolist()}, "4×4"),
        ('{"transform": [[NaN, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}', "NaN"),
        ({"transform": [[1e400, 0, 0, 0]]}, "Infinity"),
        ({"transform": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]}, "4×4"),
        ({"transform": np.eye(4).tolist(), "markers": True}, "exactly one"),
        ({}, "exactly one"),
        ({"transform": np.eye(4).tolist(), "units": "furlong"}, "frame.units"),
        ({"transform": np.eye(4).tolist(), "scale": 2}, "unknown field"),
        ("{not json", "not JSON"),
        (None, "missing"),
    ],
)
def test_bad_frames_are_422_naming_the_problem(
    client: TestClient, keys: Keys, data_dir: Path, tmp_path: Path, frame: Any, words: str
) -> None:
    env_id = make_env(client, keys)
    r = post_scan(client, keys, env_id, scan_bytes(tmp_path, "ply"), frame)
    assert r.status_code == 422, r.text
    assert r.json()["error"] == "InvalidFrame" and words in r.json()["detail"], r.json()
    assert stored_files(data_dir) == {}


@pytest.mark.parametrize(
    "body",
    [b"\xff\xd8\xff\xe0 a JPEG", b"x,y,z\n0,0,0\n", b"", b"LASF"],
    ids=["jpeg", "csv", "empty", "short-las"],
)
def test_other_files_are_415_by_content(
    client: TestClient, keys: Keys, data_dir: Path, body: bytes
) -> None:
    env_id = make_env(client, keys)
    r = post_scan(client, keys, env_id, body)
    if body:
        assert r.status_code == 415 and r.json()["error"] == "UnsupportedFileType", r.text
    else:
        assert r.status_code == 422 and r.json()["error"] == "EmptyScan", r.text
    assert stored_files(data_dir) == {}


def test_a_scan_over_max_scan_bytes_is_413(
    client: TestClient, keys: Keys, data_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    body = scan_bytes(tmp_path, "ply", n=5000)
    set_limits(monkeypatch, max_scan_bytes=len(body) - 1)
    env_id = make_env(client, keys)
    r = post_scan(client, keys, env_id, body)
    assert r.status_code == 413 and "max_scan_bytes" in r.json()["detail"], r.text
    assert stored_files(data_dir) == {}
    set_limits(monkeypatch, max_scan_bytes=len(body))
    assert post_scan(client, keys, env_id, body).status_code == 202


def test_a_read_key_cannot_upload_a_scan(client: TestClient, keys: Keys, tmp_path: Path) -> None:
    env_id = make_env(client, keys)
    r = post_scan(client, keys, env_id, scan_bytes(tmp_path, "ply"), who="read")
    assert r.status_code == 403


def test_a_scan_body_over_max_scan_bytes_is_413_before_reading(
    session_factory: sessionmaker[Session], keys: Keys, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The body cap of the scans route is max_scan_bytes (plus the framing), not the photo
    upload's: checked by BodyGuard before a byte is read (declared) or cut off (chunked)."""
    from app.core import environments

    with session_factory.begin() as s:
        env_id = environments.create(s, "line-1", CLASSES, None, None).id
    set_limits(monkeypatch, max_scan_bytes=10 * MB, max_upload_bytes=100 * MB)
    path = f"/v1/environments/{env_id}/scans"
    cap, what = body_limit("POST", path, get_settings())
    assert what == f"max_scan_bytes ({10 * MB})" and cap < 15 * MB
    chunks = list(multipart_chunks(40 * MB, "file", "big.e57"))
    for declared in (True, False):
        answer = drive(
            "POST",
            path,
            iter(chunks),
            {
                "Content-Type": f"multipart/form-data; boundary={BOUNDARY}",
                **keys.headers("capture"),
            },
            sum(map(len, chunks)) if declared else None,
        )
        assert (answer.status, answer.body["error"]) == (413, "PayloadTooLarge"), answer
        assert "max_scan_bytes" in answer.body["detail"]
        assert answer.read_bytes <= (0 if declared else cap + MB)
