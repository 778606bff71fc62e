"""Snapshot upload over HTTP: loose files and archives, idempotency, every validation case
(named file and line), limits and bombs, unsafe archive members, and that a rejected
upload leaves nothing behind."""

from __future__ import annotations

import hashlib
import io
import json
import struct
import tarfile
import zipfile
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from PIL import Image
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from app.core.models import Job, Snapshot
from app.core.settings import get_settings
from tests.app.conftest import Keys, SentTasks

Files = list[tuple[str, tuple[str, bytes, str]]]
CLASSES = ["power_drill", "bowl"]
LABELS = {
    "a0": b"0 0.5 0.5 0.2 0.3\n1 0.25 0.75 0.1 0.1 0.9\n",
    "a1": b"\n1 0.5 0.5 0.4 0.4 0.5\n",
}
CAMERAS = {
    "intrinsics": {"model": "PINHOLE", "width": 32, "height": 24, "params": [30, 30, 16, 12]},
    "poses": {"a0.jpg": np.eye(4).tolist()},
}


def image_bytes(fmt: str = "JPEG", size: tuple[int, int] = (32, 24), seed: int = 0) -> bytes:
    rng = np.random.default_rng(seed)
    pixels = rng.integers(0, 255, (size[1], size[0], 3), dtype=np.uint8)
    out = io.BytesIO()
    Image.fromarray(pixels).save(out, fmt)
    return out.getvalue()


def capture(n: int = 3, cameras: bool = True) -> dict[str, bytes]:
    """A small capture by stored name: JPEGs a0.., one PNG, labels, cameras.json."""
    files = {f"a{i}.jpg": image_bytes("JPEG", seed=i) for i in range(n - 1)}
    files[f"a{n - 1}.png"] = image_bytes("PNG", seed=n)
    files.update({f"{stem}.txt": body for stem, body in LABELS.items()})
    if cameras:
        files["cameras.json"] = json.dumps(CAMERAS).encode()
    return files


def as_parts(files: dict[str, bytes]) -> Files:
    """Loose multipart parts: images, detections, cameras by suffix."""
    parts: Files = []
    for name, body in files.items():
        if name == "cameras.json":
            parts.append(("cameras", (name, body, "application/json")))
        elif name.endswith(".txt"):
            parts.append(("detections", (name, body, "text/plain")))
        else:
            parts.append(("images", (name, body, "application/octet-stream")))
    return parts


def zip_bytes(members: dict[str, bytes], method: int = zipfile.ZIP_DEFLATED) -> bytes:
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", method) as zf:
        for name, body in members.items():
            zf.writestr(name, body)
    return out.getvalue()


def tar_bytes(members: dict[str, bytes], mode: str = "w") -> bytes:
    out = io.BytesIO()
    with tarfile.open(fileobj=out, mode=mode) as tf:  # type: ignore[call-overload]
        for name, body in members.items():
            info = tarfile.TarInfo(name)
            info.size = len(body)
            tf.addfile(info, io.BytesIO(body))
    return out.getvalue()


def nested(files: dict[str, bytes]) -> dict[str, bytes]:
    """Archive layout: images and labels in sub-folders, plus classes.txt."""
    out = {
        (f"cap/labels/{n}" if n.endswith(".txt") else n if n == "cameras.json" else f"cap/{n}"): b
        for n, b in files.items()
    }
    out["classes.txt"] = "\n".join(CLASSES).encode()
    return out


def make_env(client: TestClient, keys: Keys, name: str = "line-1") -> str:
    r = client.post(
        "/v1/environments", json={"name": name, "classes": CLASSES}, headers=keys.headers()
    )
    assert r.status_code == 201, r.text
    env_id: str = r.json()["id"]
    return env_id


def upload(
    client: TestClient, keys: Keys, env_id: str, parts: Files, key: str | None = None
) -> Any:
    headers = keys.headers("capture")
    if key is not None:
        headers["Idempotency-Key"] = key
    return client.post(f"/v1/environments/{env_id}/snapshots", files=parts, headers=headers)


def archive_part(name: str, body: bytes) -> Files:
    return [("archive", (name, body, "application/octet-stream"))]


def set_limits(monkeypatch: pytest.MonkeyPatch, **limits: int) -> None:
    for name, value in limits.items():
        monkeypatch.setenv(f"TWINDELTA_{name.upper()}", str(value))
    get_settings.cache_clear()


def stored_files(data_dir: Path) -> dict[str, str]:
    """Every file under storage (except empty staging folders), by relative path → sha256."""
    root = data_dir / "files"
    if not root.exists():
        return {}
    return {
        p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in root.rglob("*")
        if p.is_file()
    }


# --- happy paths ----------------------------------------------------------------------------


def test_upload_loose_files(
    client: TestClient, keys: Keys, sent_tasks: SentTasks, data_dir: Path
) -> None:
    env_id = make_env(client, keys)
    files = capture()
    r = upload(client, keys, env_id, as_parts(files))
    assert r.status_code == 202, r.text
    body = r.json()
    snap, job = body["snapshot"], body["job"]
    assert r.headers["location"] == f"/v1/jobs/{job['id']}"
    assert snap["seq"] == 1 and snap["state"] == "uploaded" and snap["environment"] == env_id
    assert (snap["n_images"], snap["n_detections"], snap["has_cameras"]) == (3, 3, True)
    assert snap["upload_bytes"] == sum(len(b) for b in files.values())
    assert job["kind"] == "snapshot" and job["state"] == "queued" and snap["job"] == job["id"]
    assert sent_tasks.calls == [("snapshot.process", {"job_id": job["id"]})]

    stored = stored_files(data_dir)
    prefix = f"snapshots/{snap['id']}"
    assert set(stored) == {
        f"{prefix}/images/a0.jpg",
        f"{prefix}/images/a1.jpg",
        f"{prefix}/images/a2.png",
        f"{prefix}/labels/a0.txt",
        f"{prefix}/labels/a1.txt",
        f"{prefix}/cameras.json",
    }
    assert stored[f"{prefix}/images/a0.jpg"] == hashlib.sha256(files["a0.jpg"]).hexdigest()

    read = keys.headers("read")
    got = client.get(f"/v1/snapshots/{snap['id']}", headers=read).json()
    assert got["id"] == snap["id"] and got["job"] == job["id"] and got["n_images"] == 3
    assert client.get(f"/v1/jobs/{job['id']}", headers=read).json()["state"] == "queued"

    classes_part = ("detections", ("classes.txt", "\n".join(CLASSES).encode(), "text/plain"))
    loose_classes = [*as_parts(capture(cameras=False)), classes_part]
    r2 = upload(client, keys, env_id, loose_classes)
    assert r2.status_code == 202 and r2.json()["snapshot"]["seq"] == 2
    assert r2.json()["snapshot"]["has_cameras"] is False
    history = client.get(f"/v1/environments/{env_id}/snapshots", headers=read).json()
    assert [s["seq"] for s in history] == [2, 1]


@pytest.mark.parametrize(
    ("name", "pack"),
    [
        ("cap.zip", zip_bytes),
        ("cap.zip", lambda m: zip_bytes(m, zipfile.ZIP_STORED)),
        ("cap.tar", tar_bytes),
        ("cap.tar.gz", lambda m: tar_bytes(m, "w:gz")),
    ],
)
def test_upload_archive(
    client: TestClient,
    keys: Keys,
    sent_tasks: SentTasks,
    data_dir: Path,
    name: str,
    pack: Any,
) -> None:
    env_id = make_env(client, keys)
    members = nested(capture())
    members["__MACOSX/cap/._a0.jpg"] = b"resource fork"
    r = upload(client, keys, env_id, archive_part(name, pack(members)))
    assert r.status_code == 202, r.text
    snap = r.json()["snapshot"]
    assert (snap["n_images"], snap["n_detections"], snap["has_cameras"]) == (3, 3, True)
    assert sent_tasks.names() == ["snapshot.process"]
    prefix = f"snapshots/{snap['id']}"
    assert sorted(stored_files(data_dir)) == sorted(
        [f"{prefix}/images/{n}" for n in ("a0.jpg", "a1.jpg", "a2.png")]
        + [f"{prefix}/labels/a0.txt", f"{prefix}/labels/a1.txt", f"{prefix}/cameras.json"]
    )


# --- idempotency ----------------------------------------------------------------------------


def test_idempotency_key(client: TestClient, keys: Keys, sent_tasks: SentTasks) -> None:
    env_id = make_env(client, keys)
    files = capture()
    first = upload(client, keys, env_id, as_parts(files), key="station-7/0001")
    assert first.status_code == 202
    again = upload(client, keys, env_id, as_parts(files), key="station-7/0001")
    assert again.status_code == 202 and again.headers["idempotent-replayed"] == "true"
    assert again.json()["snapshot"]["id"] == first.json()["snapshot"]["id"]
    assert again.json()["job"]["id"] == first.json()["job"]["id"]
    assert again.headers["location"] == first.headers["location"]
    # The same files in an archive are the same request.
    packed = upload(client, keys, env_id, archive_part("c.zip", zip_bytes(files)), "station-7/0001")
    assert packed.status_code == 202
    assert packed.json()["snapshot"]["id"] == first.json()["snapshot"]["id"]
    assert sent_tasks.names() == ["snapshot.process"]

    changed = dict(files, **{"a0.txt": b"1 0.5 0.5 0.2 0.2\n"})
    r = upload(client, keys, env_id, as_parts(changed), key="station-7/0001")
    assert r.status_code == 409 and r.json()["error"] == "IdempotencyKeyReused"
    other = upload(client, keys, env_id, as_parts(files), key="station-7/0002")
    assert other.status_code == 202 and other.json()["snapshot"]["seq"] == 2
    assert sent_tasks.names() == ["snapshot.process"] * 2


# --- validation: each names the file (and line) ---------------------------------------------


def _with(**changes: bytes | None) -> dict[str, bytes]:
    files = capture()
    for name, body in changes.items():
        name = name.replace("__", ".")
        if body is None:
            files.pop(name)
        else:
            files[name] = body
    return files


BAD_CAMERAS = {
    "not_json": b"{intrinsics: }",
    "params": json.dumps(
        {"intrinsics": {"model": "OPENCV", "width": 32, "height": 24, "params": [1, 2, 3, 4]}}
    ).encode(),
    "model": json.dumps(
        {"intrinsics": {"model": "FISHEYE", "width": 32, "height": 24, "params": [1, 2, 3, 4]}}
    ).encode(),
    "not_rigid": json.dumps(
        {"intrinsics": CAMERAS["intrinsics"], "poses": {"a0.jpg": (2 * np.eye(4)).tolist()}}
    ).encode(),
    "unknown_image": json.dumps(
        {"intrinsics": CAMERAS["intrinsics"], "poses": {"zz.jpg": np.eye(4).tolist()}}
    ).encode(),
}
TRUNCATED_JPEG = image_bytes("JPEG", size=(64, 48))[:300]


@pytest.mark.parametrize(
    ("files", "status", "code", "detail"),
    [
        (_with(a1__jpg=b"not an image"), 422, "InvalidImage", "a1.jpg"),
        (_with(a1__jpg=TRUNCATED_JPEG), 422, "InvalidImage", "a1.jpg"),
        (_with(a1__jpg=image_bytes("GIF")), 422, "InvalidImage", "a1.jpg"),
        (_with(a1__txt=b"1 0.5 0.5 0.1 0.1\n0 0.5 0.5 0.1\n"), 422, "InvalidDetections",
         "a1.txt line 2: expected 5 or 6 numbers"),
        (_with(a1__txt=b"0 0.5 0.5 0.1 0.1 0.3 0.2\n"), 422, "InvalidDetections", "a1.txt line 1"),
        (_with(a1__txt=b"0 0.5 abc 0.1 0.1\n"), 422, "InvalidDetections",
         "a1.txt line 1: 'abc' is not a number"),
        (_with(a1__txt=b"0 0.5 0.5 0.1 0.1\n\n7 0.5 0.5 0.1 0.1\n"), 422, "UnknownClass",
         "a1.txt line 3: class id 7"),
        (_with(a1__txt=b"1.5 0.5 0.5 0.1 0.1\n"), 422, "InvalidDetections", "not an integer"),
        (_with(a0__txt=b"0 1.5 0.5 0.1 0.1\n"), 422, "InvalidDetections",
         "a0.txt line 1: cx = 1.5 is outside 0..1"),
        (_with(a0__txt=b"0 0.5 0.5 0.1 -0.1\n"), 422, "InvalidDetections", "h = -0.1"),
        (_with(a0__txt=b"0 0.5 0.5 0.1 0.1 nan\n"), 422, "InvalidDetections", "confidence"),
        (_with(a0__txt=b"0 0.5 0.5 0.1 \xff\n"), 422, "InvalidDetections", "line 1: not UTF-8"),
        (_with(zz__txt=b"0 0.5 0.5 0.1 0.1\n"), 422, "OrphanDetections", "zz.txt"),
        (_with(a0__png=image_bytes("PNG")), 422, "DuplicateImage", "a0"),
        (_with(a3__gif=image_bytes("GIF")), 415, "UnsupportedFileType", "a3.gif"),
        (_with(a1__jpg=None, a2__png=None), 422, "TooFewImages", "at least 3"),
        *[
            (_with(cameras__json=body), 422, "InvalidCameras", "cameras.json")
            for body in BAD_CAMERAS.values()
        ],
    ],
    ids=[
        "undecodable", "truncated", "gif-as-jpg", "four-numbers", "seven-numbers",
        "not-a-number", "unknown-class", "fractional-class", "coordinate", "negative",
        "nan", "not-utf8", "orphan", "duplicate-stem", "unsupported", "too-few",
        *[f"cameras-{k}" for k in BAD_CAMERAS],
    ],
)  # fmt: skip
def test_validation_errors(
    client: TestClient,
    keys: Keys,
    sent_tasks: SentTasks,
    files: dict[str, bytes],
    status: int,
    code: str,
    detail: str,
) -> None:
    env_id = make_env(client, keys)
    r = upload(client, keys, env_id, as_parts(files))
    assert (r.status_code, r.json()["error"]) == (status, code), r.text
    assert detail in r.json()["detail"]
    # The same content inside an archive is rejected the same way, naming the member.
    r = upload(client, keys, env_id, archive_part("c.zip", zip_bytes(nested(files))))
    assert (r.status_code, r.json()["error"]) == (status, code), r.text
    assert sent_tasks.names() == []


def test_cameras_error_names_the_json_line(client: TestClient, keys: Keys) -> None:
    env_id = make_env(client, keys)
    r = upload(client, keys, env_id, as_parts(_with(cameras__json=b'{\n  "intrinsics": ,\n}')))
    assert r.status_code == 422 and "cameras.json line 2" in r.json()["detail"]


def test_request_shape_errors(client: TestClient, keys: Keys) -> None:
    env_id = make_env(client, keys)
    r = upload(client, keys, env_id, [("detections", ("a.txt", b"", "text/plain"))])
    assert r.status_code == 422 and r.json()["error"] == "InvalidUpload"
    both = as_parts(capture()) + archive_part("c.zip", zip_bytes(capture()))
    r = upload(client, keys, env_id, both)
    assert r.status_code == 422 and r.json()["error"] == "InvalidUpload"
    r = upload(client, keys, env_id, archive_part("c.rar", b"Rar!"))
    assert r.status_code == 415 and r.json()["error"] == "UnsupportedFileType"
    r = upload(client, keys, env_id, archive_part("c.zip", b"PK not really"))
    assert r.status_code == 422 and r.json()["error"] == "InvalidArchive"
    r = upload(client, keys, env_id, archive_part("c.tar.gz", b"\x1f\x8b garbage"))
    assert r.status_code == 422 and r.json()["error"] == "InvalidArchive"
    members = dict(nested(capture()), **{"cap/notes.pdf": b"%PDF"})
    r = upload(client, keys, env_id, archive_part("c.zip", zip_bytes(members)))
    assert r.status_code == 415 and "cap/notes.pdf" in r.json()["detail"]
    members = dict(nested(capture()), **{"classes.txt": b"power_drill\nmug\n"})
    r = upload(client, keys, env_id, archive_part("c.zip", zip_bytes(members)))
    assert r.status_code == 422 and r.json()["error"] == "ClassesMismatch"
    assert "classes.txt line 2" in r.json()["detail"]
    r = upload(client, keys, "no-such-env", as_parts(capture()))
    assert r.status_code == 404
    r = client.post(
        f"/v1/environments/{env_id}/snapshots",
        files=as_parts(capture()),
        headers=keys.headers("read"),
    )
    assert r.status_code == 403


# --- limits and bombs -----------------------------------------------------------------------


@pytest.mark.parametrize(
    ("limits", "code", "detail"),
    [
        ({"max_upload_files": 4}, "TooManyFiles", "more than 4 files"),
        ({"max_file_bytes": 1000}, "PayloadTooLarge", "larger than 1000 bytes"),
        ({"max_upload_bytes": 2000}, "PayloadTooLarge", "the upload is larger than 2000"),
        ({"max_image_pixels": 500}, "ImageTooLarge", "32×24 = 768 pixels"),
        ({"max_detection_lines": 1}, "TooManyDetections", "a0.txt line 2"),
    ],
)
def test_limits_are_413(
    client: TestClient,
    keys: Keys,
    monkeypatch: pytest.MonkeyPatch,
    limits: dict[str, int],
    code: str,
    detail: str,
) -> None:
    env_id = make_env(client, keys)
    set_limits(monkeypatch, **limits)
    r = upload(client, keys, env_id, as_parts(capture()))
    assert (r.status_code, r.json()["error"]) == (413, code), r.text
    assert detail in r.json()["detail"]


def png_claiming(width: int, height: int) -> bytes:
    """A tiny PNG whose header claims ``width`` × ``height`` pixels."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        crc = zlib.crc32(kind + data) & 0xFFFFFFFF
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", crc)

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(b"\0" * 64))
        + chunk(b"IEND", b"")
    )


@pytest.mark.parametrize("size", [(100_000, 100_000), (10_000, 6_000)])
def test_decompression_bomb_image(client: TestClient, keys: Keys, size: tuple[int, int]) -> None:
    env_id = make_env(client, keys)
    bomb = png_claiming(*size)
    assert len(bomb) < 200
    r = upload(client, keys, env_id, as_parts(_with(a2__png=bomb)))
    assert (r.status_code, r.json()["error"]) == (413, "ImageTooLarge"), r.text
    assert "a2.png" in r.json()["detail"]


def test_zip_bomb_is_bounded_by_bytes_read(
    client: TestClient, keys: Keys, monkeypatch: pytest.MonkeyPatch
) -> None:
    env_id = make_env(client, keys)
    # The ratio check (test_upload_limits) would refuse it before inflating: turn it off
    # here to see the per-file limit stop a member while it is being written.
    set_limits(monkeypatch, max_file_bytes=1_000_000, max_archive_ratio=1_000_000)
    members = dict(nested(capture()), **{"cap/a9.jpg": b"\0" * 20_000_000})
    packed = zip_bytes(members)
    assert len(packed) < 100_000
    r = upload(client, keys, env_id, archive_part("c.zip", packed))
    assert (r.status_code, r.json()["error"]) == (413, "PayloadTooLarge"), r.text
    assert "cap/a9.jpg: larger than 1000000 bytes" in r.json()["detail"]


def test_zip_with_lying_sizes(client: TestClient, keys: Keys) -> None:
    """A member whose declared size is smaller than its data is never inflated past it."""
    env_id = make_env(client, keys)
    members = nested(capture())
    members["cap/a9.jpg"] = b"\0" * 5_000_000
    packed = bytearray(zip_bytes(members))
    name = b"cap/a9.jpg"
    local = packed.find(b"PK\x03\x04")
    while packed[local + 30 : local + 30 + len(name)] != name:
        local = packed.find(b"PK\x03\x04", local + 4)
    central = packed.find(b"PK\x01\x02")
    while packed[central + 46 : central + 46 + len(name)] != name:
        central = packed.find(b"PK\x01\x02", central + 4)
    struct.pack_into("<I", packed, local + 22, 100)
    struct.pack_into("<I", packed, central + 24, 100)
    r = upload(client, keys, env_id, archive_part("c.zip", bytes(packed)))
    assert (r.status_code, r.json()["error"]) == (422, "InvalidArchive"), r.text
    assert "cap/a9.jpg" in r.json()["detail"]


# --- unsafe archive members -----------------------------------------------------------------


@pytest.mark.parametrize("member", ["../evil.jpg", "/etc/evil.jpg", "cap/../../evil.txt"])
def test_zip_path_traversal(client: TestClient, keys: Keys, data_dir: Path, member: str) -> None:
    env_id = make_env(client, keys)
    members = dict(nested(capture()), **{member: image_bytes()})
    r = upload(client, keys, env_id, archive_part("c.zip", zip_bytes(members)))
    assert (r.status_code, r.json()["error"]) == (422, "UnsafeArchiveMember"), r.text
    assert member in r.json()["detail"]
    assert stored_files(data_dir) == {}
    assert not list(data_dir.rglob("evil*"))


def test_zip_symlink_member(client: TestClient, keys: Keys) -> None:
    env_id = make_env(client, keys)
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as zf:
        for name, body in nested(capture()).items():
            zf.writestr(name, body)
        link = zipfile.ZipInfo("cap/link.jpg")
        link.external_attr = (0o120777 << 16) | 0
        zf.writestr(link, "/etc/passwd")
    r = upload(client, keys, env_id, archive_part("c.zip", out.getvalue()))
    assert (r.status_code, r.json()["error"]) == (422, "UnsafeArchiveMember"), r.text


@pytest.mark.parametrize(
    ("name", "kind"),
    [
        ("../evil.jpg", tarfile.REGTYPE),
        ("/abs/evil.jpg", tarfile.REGTYPE),
        ("cap/link.jpg", tarfile.SYMTYPE),
        ("cap/hard.jpg", tarfile.LNKTYPE),
        ("cap/dev.jpg", tarfile.CHRTYPE),
        ("cap/fifo.jpg", tarfile.FIFOTYPE),
    ],
)
def test_tar_unsafe_members(
    client: TestClient, keys: Keys, data_dir: Path, name: str, kind: bytes
) -> None:
    env_id = make_env(client, keys)
    out = io.BytesIO()
    with tarfile.open(fileobj=out, mode="w") as tf:
        for member, body in nested(capture()).items():
            info = tarfile.TarInfo(member)
            info.size = len(body)
            tf.addfile(info, io.BytesIO(body))
        bad = tarfile.TarInfo(name)
        bad.type = kind
        payload = image_bytes() if kind == tarfile.REGTYPE else b""
        bad.size = len(payload)
        if kind in (tarfile.SYMTYPE, tarfile.LNKTYPE):
            bad.linkname = "/etc/passwd"
        tf.addfile(bad, io.BytesIO(payload))
    r = upload(client, keys, env_id, archive_part("c.tar", out.getvalue()))
    assert (r.status_code, r.json()["error"]) == (422, "UnsafeArchiveMember"), r.text
    assert name in r.json()["detail"]
    assert stored_files(data_dir) == {}


# --- a rejected upload leaves nothing behind ------------------------------------------------


def test_rejections_leave_nothing_behind(
    client: TestClient,
    keys: Keys,
    session: Session,
    sent_tasks: SentTasks,
    data_dir: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    env_id = make_env(client, keys)
    good = upload(client, keys, env_id, as_parts(capture()), key="k1")
    assert good.status_code == 202
    first = good.json()["snapshot"]
    files_before = stored_files(data_dir)
    assert len(files_before) == 6

    bad_uploads: list[Files] = [
        as_parts(_with(a2__jpg=b"junk")),  # fails after staging every file
        as_parts(_with(a0__txt=b"0 0.5 0.5 0.1\n")),
        as_parts(_with(zz__txt=b"0 0.5 0.5 0.1 0.1\n")),
        archive_part("c.zip", zip_bytes(dict(nested(capture()), **{"../x.jpg": b"x"}))),
        archive_part("c.tar", tar_bytes(nested(capture()))[:3000]),
        as_parts(_with(a1__png=png_claiming(100_000, 100_000))),
    ]
    for parts in bad_uploads:
        r = upload(client, keys, env_id, parts)
        assert 400 <= r.status_code < 500, r.text
    r = upload(client, keys, env_id, as_parts(_with(a0__txt=b"1 0.5 0.5 0.1 0.1\n")), key="k1")
    assert r.status_code == 409
    set_limits(monkeypatch, max_upload_bytes=3000)
    r = upload(client, keys, env_id, as_parts(capture()))
    assert r.status_code == 413

    assert stored_files(data_dir) == files_before
    tmp = data_dir / "files" / ".tmp"
    assert not tmp.exists() or list(tmp.iterdir()) == []
    assert session.scalar(select(func.count()).select_from(Snapshot)) == 1
    assert session.scalar(select(func.count()).select_from(Job)) == 1
    snap = session.get(Snapshot, first["id"])
    assert snap is not None and (snap.seq, snap.n_images, snap.n_detections) == (1, 3, 3)
    assert sent_tasks.names() == ["snapshot.process"]


def test_comparison_options_are_checked_before_the_snapshots_state(
    client: TestClient, keys: Keys, sent_tasks: SentTasks
) -> None:
    """A requested comparison with an option the compare stage would refuse is a 422 naming
    it; with good options the two uploaded (not yet reconstructed) snapshots are a 409."""
    env_id = make_env(client, keys)
    ids = [upload(client, keys, env_id, as_parts(capture())).json()["snapshot"]["id"] for _ in "ab"]
    url = f"/v1/environments/{env_id}/comparisons"
    body = {"before": ids[0], "after": ids[1]}
    r = client.post(url, json={**body, "options": {"use_visibility": "no"}}, headers=keys.headers())
    assert r.status_code == 422 and "options.use_visibility must be a bool" in r.json()["detail"]
    r = client.post(url, json={**body, "options": {"preset": "strict"}}, headers=keys.headers())
    assert r.status_code == 422 and "unknown compare preset 'strict'" in r.json()["detail"]
    r = client.post(url, json={**body, "options": {"preset": "lod"}}, headers=keys.headers())
    assert r.status_code == 409 and r.json()["error"] == "SnapshotNotReconstructed"
