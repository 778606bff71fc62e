"""Request bodies are authenticated and capped before they are read: the application is
driven as ASGI with a body source that counts what the server pulled, so "nothing was read"
is measured, not assumed."""

from __future__ import annotations

import asyncio
import io
import json
import struct
import tarfile
import zipfile
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy.orm import Session, sessionmaker

from app.api.limits import body_limit
from app.core.errors import DomainError
from app.core.settings import get_settings
from app.main import create_app
from tests.app.api.test_snapshots_upload import (
    archive_part,
    as_parts,
    capture,
    make_env,
    nested,
    tar_bytes,
    upload,
    zip_bytes,
)
from tests.app.conftest import Keys, SentTasks

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


# --- archives, images and error details (hostile captures) ----------------------------------


def staged_bytes(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Record the bytes each staged file reached on disk (its final or rejected size)."""
    from app.core import ingest

    sizes: list[int] = []
    real = ingest.staging._stage_file

    def counting(staging: Any, kind: str, name: str, where: str, source: Any) -> Any:
        target = staging.root / kind / name if kind else staging.root / name
        try:
            staged = real(staging, kind, name, where, source)
        finally:
            sizes.append(target.stat().st_size if target.exists() else 0)
        return staged

    monkeypatch.setattr(ingest.staging, "_stage_file", counting)
    return sizes


def test_zip_bomb_is_refused_before_anything_is_inflated(
    client: TestClient, keys: Keys, monkeypatch: pytest.MonkeyPatch, data_dir: Path
) -> None:
    env_id = make_env(client, keys)
    members = dict(nested(capture()), **{"cap/a9.jpg": b"\0" * 150 * MB})
    packed = zip_bytes(members)
    assert len(packed) < 200_000  # ~1000× smaller than what it unpacks to
    sizes = staged_bytes(monkeypatch)
    r = upload(client, keys, env_id, archive_part("c.zip", packed))
    assert (r.status_code, r.json()["error"]) == (413, "ArchiveBomb"), r.text
    assert "max_archive_ratio" in r.json()["detail"]
    assert sum(sizes) == 0  # refused from the declared sizes: nothing was written
    tmp = data_dir / "files" / ".tmp"
    assert not tmp.exists() or list(tmp.iterdir()) == []


def test_tar_gz_bomb_stops_at_the_limit_while_extracting(
    client: TestClient, keys: Keys, monkeypatch: pytest.MonkeyPatch
) -> None:
    env_id = make_env(client, keys)
    members = dict(nested(capture()), **{"cap/a9.jpg": b"\0" * 150 * MB})
    packed = tar_bytes(members, "w:gz")
    assert len(packed) < 400_000
    sizes = staged_bytes(monkeypatch)
    r = upload(client, keys, env_id, archive_part("c.tar.gz", packed))
    assert (r.status_code, r.json()["error"]) == (413, "ArchiveBomb"), r.text
    # at most max_archive_ratio × what was read of the archive, plus the slack
    assert sum(sizes) <= 100 * len(packed) + 2 * MB, sizes


def test_every_archive_member_counts(
    client: TestClient, keys: Keys, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Folders are members too: an archive of a few files and thousands of folder entries
    is refused, however few files it holds."""
    env_id = make_env(client, keys)
    monkeypatch.setenv("TWINDELTA_MAX_ARCHIVE_MEMBERS", "500")
    get_settings.cache_clear()
    out = io.BytesIO()
    with tarfile.open(fileobj=out, mode="w:gz") as tf:
        for i in range(3000):
            info = tarfile.TarInfo(f"d/{i}")
            info.type = tarfile.DIRTYPE
            tf.addfile(info)
        for name, body in nested(capture()).items():
            info = tarfile.TarInfo(name)
            info.size = len(body)
            tf.addfile(info, io.BytesIO(body))
    r = upload(client, keys, env_id, archive_part("c.tar.gz", out.getvalue()))
    assert (r.status_code, r.json()["error"]) == (413, "TooManyFiles"), r.text
    assert "more than 500 archive members" in r.json()["detail"]
    zipped = io.BytesIO()
    with zipfile.ZipFile(zipped, "w") as zf:
        for i in range(3000):
            zf.writestr(f"d/{i}/", b"")
        for name, body in nested(capture()).items():
            zf.writestr(name, body)
    r = upload(client, keys, env_id, archive_part("c.zip", zipped.getvalue()))
    assert (r.status_code, r.json()["error"]) == (413, "TooManyFiles"), r.text


def png_16bit_rgba(width: int, height: int) -> bytes:
    """A valid PNG of ``width`` × ``height`` 16-bit RGBA zeros, deflated row by row."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        crc = zlib.crc32(kind + data) & 0xFFFFFFFF
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", crc)

    deflate = zlib.compressobj(9)
    row = b"\0" * (1 + width * 8)
    idat = b"".join(deflate.compress(row) for _ in range(height)) + deflate.flush()
    header = struct.pack(">IIBBBBB", width, height, 16, 6, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")
    )


def test_png_decoded_size_is_checked_before_decoding(
    client: TestClient, keys: Keys, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Under the pixel limit (1000×1000 < 2,000,000 pixels), over the decoded-bytes budget
    (16-bit RGBA: 8,000,000 bytes > 4,000,000)."""
    env_id = make_env(client, keys)
    monkeypatch.setenv("TWINDELTA_MAX_IMAGE_PIXELS", "2000000")
    monkeypatch.setenv("TWINDELTA_MAX_IMAGE_DECODED_BYTES", "4000000")
    get_settings.cache_clear()
    files = capture()
    files["a2.png"] = png_16bit_rgba(1000, 1000)
    r = upload(client, keys, env_id, as_parts(files))
    assert (r.status_code, r.json()["error"]) == (413, "ImageTooLarge"), r.text
    assert "a2.png: 1000×1000 at 8 bytes a pixel" in r.json()["detail"]


def test_the_reviewers_7000_square_16bit_png_is_refused_by_default() -> None:
    from app.core import ingest

    settings = get_settings()
    bomb = png_16bit_rgba(7000, 7000)
    assert len(bomb) < 500_000
    assert settings.max_image_pixels >= 7000 * 7000  # the pixel count alone lets it through
    with pytest.raises(DomainError) as err:
        ingest.probe_image(
            io.BytesIO(bomb), "big.png", settings.max_image_pixels, settings.max_image_decoded_bytes
        )
    assert (err.value.status_code, err.value.code) == (413, "ImageTooLarge")


def test_error_details_never_show_server_paths(
    client: TestClient, keys: Keys, data_dir: Path
) -> None:
    env_id = make_env(client, keys)
    files = capture()
    files["a0.jpg"] = b"this is not an image at all"
    r = upload(client, keys, env_id, as_parts(files))
    assert (r.status_code, r.json()["error"]) == (422, "InvalidImage"), r.text
    detail = r.json()["detail"]
    assert detail.startswith("a0.jpg: ")
    for leak in (str(data_dir), "/.tmp/", "name="):
        assert leak not in detail, detail
    # the same through an archive member
    members = dict(nested(capture()), **{"cap/a0.jpg": b"junk"})
    r = upload(client, keys, env_id, archive_part("c.zip", zip_bytes(members)))
    assert r.status_code == 422 and str(data_dir) not in r.json()["detail"], r.text


def test_ply_declaring_more_vertices_than_it_holds_is_refused_at_upload(
    client: TestClient, keys: Keys, sent_tasks: SentTasks
) -> None:
    header = (
        "ply\nformat binary_little_endian 1.0\nelement vertex 2000000000\n"
        "property float x\nproperty float y\nproperty float z\nend_header\n"
    )
    body = header.encode() + b"\0" * 36
    r = client.post(
        "/v1/objects",
        files={"file": ("bomb.ply", body, "application/octet-stream")},
        data={"name": "drill"},
        headers=keys.headers(),
    )
    assert (r.status_code, r.json()["error"]) == (422, "InvalidInput"), r.text
    assert "2000000000 vertex elements" in r.json()["detail"]
    assert sent_tasks.names() == []
    honest = header.replace("2000000000", "3").encode() + b"\0" * 36
    r = client.post(
        "/v1/objects",
        files={"file": ("ok.ply", honest, "application/octet-stream")},
        data={"name": "drill"},
        headers=keys.headers(),
    )
    assert r.status_code == 202, r.text
