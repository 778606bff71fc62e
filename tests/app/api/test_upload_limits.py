"""Request bodies are authenticated and capped before they are read: the application is
driven as ASGI with a body source that counts what the server pulled, so "nothing was read"
is measured, not assumed."""

from __future__ import annotations

import asyncio
import json
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from sqlalchemy.orm import Session, sessionmaker

from app.api.limits import body_limit
from app.core.settings import get_settings
from app.main import create_app
from tests.app.api.test_snapshots_upload import capture
from tests.app.conftest import Keys

MB = 1024**2
BOUNDARY = "twindeltaboundary"


@dataclass
class Answer:
    status: int
    body: dict[str, str]
    read_bytes: int  # how much of the body the server pulled


def multipart_chunks(total: int, field: str = "archive", name: str = "c.zip") -> Iterator[bytes]:
    """One file part of about ``total`` bytes, produced 1 MiB at a time (never held whole)."""
    yield (
        f'--{BOUNDARY}\r\nContent-Disposition: form-data; name="{field}"; '
        f'filename="{name}"\r\nContent-Type: application/octet-stream\r\n\r\n'
    ).encode()
    block = b"x" * MB
    for _ in range(total // MB):
        yield block
    yield f"\r\n--{BOUNDARY}--\r\n".encode()


def drive(
    method: str,
    path: str,
    chunks: Iterator[bytes],
    headers: dict[str, str],
    content_length: int | None,
) -> Answer:
    """Send one request straight to the ASGI app; count the body bytes it receives."""
    app = create_app()
    read = 0
    sent: list[dict[str, object]] = []
    pending = list(chunks)

    async def receive() -> dict[str, object]:
        nonlocal read
        if not pending:
            return {"type": "http.disconnect"}
        chunk = pending.pop(0)
        read += len(chunk)
        return {"type": "http.request", "body": chunk, "more_body": bool(pending)}

    async def send(message: dict[str, object]) -> None:
        sent.append(message)

    raw = [(k.lower().encode(), v.encode()) for k, v in headers.items()]
    if content_length is not None:
        raw.append((b"content-length", str(content_length).encode()))
    else:
        raw.append((b"transfer-encoding", b"chunked"))
    scope = {
        "type": "http",
        "asgi": {"version": "3.0"},
        "http_version": "1.1",
        "method": method,
        "scheme": "http",
        "path": path,
        "raw_path": path.encode(),
        "query_string": b"",
        "root_path": "",
        "headers": raw,
        "client": ("127.0.0.1", 1234),
        "server": ("127.0.0.1", 80),
    }
    asyncio.run(app(scope, receive, send))  # type: ignore[arg-type]
    start = next(m for m in sent if m["type"] == "http.response.start")
    body = b"".join(m.get("body", b"") for m in sent if m["type"] == "http.response.body")  # type: ignore[misc]
    return Answer(int(start["status"]), json.loads(body), read)  # type: ignore[call-overload]


def make_env_id(session_factory: sessionmaker[Session]) -> str:
    from app.core import environments

    with session_factory.begin() as s:
        return environments.create(s, "line-1", ["power_drill", "bowl"], None, None).id


@pytest.mark.parametrize("declared", [True, False], ids=["content-length", "chunked"])
def test_unauthenticated_upload_is_401_before_reading(
    session_factory: sessionmaker[Session], keys: Keys, data_dir: Path, declared: bool
) -> None:
    env_id = make_env_id(session_factory)
    size = 80 * MB
    chunks = list(multipart_chunks(size))
    for headers in (
        {},
        {"Authorization": "Bearer td_not_a_key_at_all_0123456789"},
    ):
        answer = drive(
            "POST",
            f"/v1/environments/{env_id}/snapshots",
            iter(chunks),
            {"Content-Type": f"multipart/form-data; boundary={BOUNDARY}", **headers},
            sum(map(len, chunks)) if declared else None,
        )
        assert (answer.status, answer.body["error"]) == (401, "Unauthorized"), answer
        assert answer.read_bytes == 0
    staging = data_dir / "files" / ".tmp"
    assert not staging.exists() or not any(staging.iterdir())


def test_unauthenticated_json_and_object_bodies_are_401_before_reading(
    session_factory: sessionmaker[Session], keys: Keys
) -> None:
    answer = drive(
        "POST",
        "/v1/environments",
        iter([b'{"name": "x", "classes": ["a"]}']),
        {"Content-Type": "application/json"},
        31,
    )
    assert (answer.status, answer.read_bytes) == (401, 0), answer
    answer = drive(
        "POST",
        "/v1/objects",
        multipart_chunks(3 * MB, "file", "m.ply"),
        {"Content-Type": f"multipart/form-data; boundary={BOUNDARY}"},
        None,
    )
    assert (answer.status, answer.read_bytes) == (401, 0), answer


@pytest.mark.parametrize("declared", [True, False], ids=["content-length", "chunked"])
def test_large_json_body_is_413_without_reading_it(
    session_factory: sessionmaker[Session], keys: Keys, declared: bool
) -> None:
    cap = get_settings().max_json_bytes
    filler = b" " * MB
    chunks = [b'{"name": "x", "classes": ["a"], "reference": {"pad": "'] + [filler] * 80 + [b'"}}']
    answer = drive(
        "POST",
        "/v1/environments",
        iter(chunks),
        {"Content-Type": "application/json", **keys.headers()},
        sum(map(len, chunks)) if declared else None,
    )
    assert (answer.status, answer.body["error"]) == (413, "PayloadTooLarge"), answer
    assert "max_json_bytes" in answer.body["detail"]
    if declared:
        assert answer.read_bytes == 0
    else:  # cut off at the cap, give or take the chunk that crossed it
        assert answer.read_bytes <= cap + MB


def test_upload_body_over_the_upload_limit_is_413_before_reading(
    session_factory: sessionmaker[Session], keys: Keys, monkeypatch: pytest.MonkeyPatch
) -> None:
    env_id = make_env_id(session_factory)
    monkeypatch.setenv("TWINDELTA_MAX_UPLOAD_BYTES", str(10 * MB))
    get_settings.cache_clear()
    chunks = list(multipart_chunks(40 * MB))
    for declared in (True, False):
        answer = drive(
            "POST",
            f"/v1/environments/{env_id}/snapshots",
            iter(chunks),
            {
                "Content-Type": f"multipart/form-data; boundary={BOUNDARY}",
                **keys.headers("capture"),
            },
            sum(map(len, chunks)) if declared else None,
        )
        assert (answer.status, answer.body["error"]) == (413, "PayloadTooLarge"), answer
        assert "max_upload_bytes" in answer.body["detail"]
        cap, _ = body_limit("POST", f"/v1/environments/{env_id}/snapshots", get_settings())
        assert cap < 15 * MB  # the configured 10 MiB plus the multipart framing allowance
        assert answer.read_bytes <= (0 if declared else cap + MB)


def test_authenticated_uploads_and_json_still_work(
    session_factory: sessionmaker[Session], keys: Keys
) -> None:
    """The guard lets a valid key's bodies through: a capture-scoped key uploads, an admin
    key posts JSON, and a key without the route's scope still gets the route's 403."""
    env_id = make_env_id(session_factory)
    parts: list[bytes] = []
    for name, body in capture().items():
        field = (
            "cameras"
            if name == "cameras.json"
            else "detections"
            if name.endswith(".txt")
            else "images"
        )
        parts.append(
            f'--{BOUNDARY}\r\nContent-Disposition: form-data; name="{field}"; '
            f'filename="{name}"\r\n\r\n'.encode()
            + body
            + b"\r\n"
        )
    parts.append(f"--{BOUNDARY}--\r\n".encode())
    content_type = {"Content-Type": f"multipart/form-data; boundary={BOUNDARY}"}
    answer = drive(
        "POST",
        f"/v1/environments/{env_id}/snapshots",
        iter(parts),
        {**content_type, **keys.headers("capture")},
        sum(map(len, parts)),
    )
    assert answer.status == 202, answer
    answer = drive(
        "POST",
        f"/v1/environments/{env_id}/snapshots",
        iter(parts),
        {**content_type, **keys.headers("read")},
        sum(map(len, parts)),
    )
    assert answer.status == 403, answer
    body = json.dumps({"name": "line-2", "classes": ["a"]}).encode()
    answer = drive(
        "POST",
        "/v1/environments",
        iter([body]),
        {"Content-Type": "application/json", **keys.headers()},
        len(body),
    )
    assert answer.status == 201, answer
