"""Resumable uploads (tus 1.0) through the app: creation, offsets, chunks, every error
status, termination, expiry, and the archive becoming a snapshot through the single
upload's ingest (same checks, same Idempotency-Key semantics)."""

from __future__ import annotations

import base64
import hashlib
from datetime import timedelta
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from httpx import Response
from sqlalchemy import func, select
from sqlalchemy.orm import Session, sessionmaker

from app.core import uploads
from app.core.errors import Conflict
from app.core.models import ResumableUpload, Snapshot, utcnow
from app.core.settings import get_settings
from app.core.storage import LocalStorage
from tests.app.api.test_snapshots_upload import capture, make_env, nested, set_limits, zip_bytes
from tests.app.conftest import Keys, SentTasks
from tests.app.core.test_uploads import spooled

TUS = {"Tus-Resumable": "1.0.0"}
OCTETS = {**TUS, "Content-Type": "application/offset+octet-stream"}


def metadata(**values: str) -> str:
    return ",".join(f"{k} {base64.b64encode(v.encode()).decode()}" for k, v in values.items())


def create(
    client: TestClient, keys: Keys, env_id: str, body: bytes, which: str = "capture", **meta: str
) -> Response:
    headers = {
        **keys.headers(which),
        **TUS,
        "Upload-Length": str(len(body)),
        "Upload-Metadata": metadata(
            **{"environment_id": env_id, "filename": "capture.zip", **meta}
        ),
    }
    return client.post("/v1/uploads", headers=headers)


def patch(
    client: TestClient, keys: Keys, url: str, offset: int, chunk: bytes, **headers: str
) -> Response:
    return client.patch(
        url,
        content=chunk,
        headers={**keys.headers("capture"), **OCTETS, "Upload-Offset": str(offset), **headers},
    )


def head(client: TestClient, keys: Keys, url: str) -> Response:
    return client.head(url, headers={**keys.headers("capture"), **TUS})


def archive() -> bytes:
    return zip_bytes(nested(capture()))


def count_snapshots(session: Session) -> int:
    return session.scalar(select(func.count()).select_from(Snapshot)) or 0


def test_options_says_what_the_server_speaks(client: TestClient, keys: Keys) -> None:
    r = client.options("/v1/uploads", headers=keys.headers("capture"))
    assert r.status_code == 204
    assert r.headers["Tus-Version"] == "1.0.0"
    assert r.headers["Tus-Resumable"] == "1.0.0"
    assert set(r.headers["Tus-Extension"].split(",")) == {
        "creation",
        "termination",
        "checksum",
        "expiration",
    }
    assert int(r.headers["Tus-Max-Size"]) == get_settings().max_upload_bytes
    assert "sha1" in r.headers["Tus-Checksum-Algorithm"].split(",")


def test_chunks_with_a_resume_become_one_snapshot(
    client: TestClient, keys: Keys, sent_tasks: SentTasks, session_factory: sessionmaker[Session]
) -> None:
    env_id = make_env(client, keys)
    body = archive()
    r = create(client, keys, env_id, body)
    assert r.status_code == 201, r.text
    url = r.headers["Location"]
    assert url.startswith("/v1/uploads/") and "Upload-Expires" in r.headers
    assert r.headers["Tus-Resumable"] == "1.0.0"
    third = len(body) // 3
    r = patch(client, keys, url, 0, body[:third])
    assert r.status_code == 204, r.text
    assert r.headers["Upload-Offset"] == str(third)
    r = head(client, keys, url)
    assert r.status_code == 200
    assert r.headers["Upload-Offset"] == str(third)
    assert r.headers["Upload-Length"] == str(len(body))
    assert r.headers["Cache-Control"] == "no-store"
    sha1 = base64.b64encode(hashlib.sha1(body[third:]).digest()).decode()
    r = patch(client, keys, url, third, body[third:], **{"Upload-Checksum": f"sha1 {sha1}"})
    assert r.status_code == 204, r.text
    snapshot_id, job_id = r.headers["Twindelta-Snapshot"], r.headers["Twindelta-Job"]
    assert r.headers["Location"] == f"/v1/jobs/{job_id}"
    assert sent_tasks.names() == ["snapshot.process"]
    snap = client.get(f"/v1/snapshots/{snapshot_id}", headers=keys.headers("admin")).json()
    assert snap["n_images"] == 3 and snap["state"] == "uploaded"
    info = client.get(url, headers=keys.headers("capture")).json()
    assert info["state"] == "completed" and info["offset"] == len(body)
    assert (info["snapshot"], info["job"]) == (snapshot_id, job_id)
    r = head(client, keys, url)
    assert r.headers["Twindelta-Snapshot"] == snapshot_id
    assert not (get_settings().resolved_storage_dir / "uploads" / url.rsplit("/", 1)[1]).exists()
    # The last PATCH again (its answer was lost): the same result, no second snapshot.
    r = patch(client, keys, url, len(body), b"")
    assert r.status_code == 204 and r.headers["Twindelta-Snapshot"] == snapshot_id
    with session_factory() as s:
        assert count_snapshots(s) == 1


def test_same_idempotency_key_twice_makes_one_snapshot(
    client: TestClient, keys: Keys, sent_tasks: SentTasks, session_factory: sessionmaker[Session]
) -> None:
    env_id = make_env(client, keys)
    body = archive()
    found = set()
    for _ in range(2):  # two separate uploads (no sha256: no reuse at creation)
        url = create(client, keys, env_id, body, idempotency_key="station-1/0001").headers[
            "Location"
        ]
        r = patch(client, keys, url, 0, body)
        assert r.status_code == 204, r.text
        found.add(r.headers["Twindelta-Snapshot"])
    assert len(found) == 1
    with session_factory() as s:
        assert count_snapshots(s) == 1
    other = zip_bytes(nested(capture(n=4)))
    url = create(client, keys, env_id, other, idempotency_key="station-1/0001").headers["Location"]
    r = patch(client, keys, url, 0, other)
    assert r.status_code == 409 and r.json()["error"] == "IdempotencyKeyReused"


def test_creation_with_key_and_sha256_resumes_the_earlier_upload(
    client: TestClient, keys: Keys, sent_tasks: SentTasks
) -> None:
    env_id = make_env(client, keys)
    body = archive()
    meta = {"idempotency_key": "k-7", "sha256": hashlib.sha256(body).hexdigest()}
    first = create(client, keys, env_id, body, **meta)
    url = first.headers["Location"]
    assert patch(client, keys, url, 0, body[:100]).status_code == 204
    again = create(client, keys, env_id, body, **meta)
    assert again.status_code == 201
    assert again.headers["Location"] == url
    assert again.headers["Idempotent-Replayed"] == "true"
    assert again.headers["Upload-Offset"] == "100"
    r = patch(client, keys, url, 100, body[100:])
    assert r.status_code == 204
    done = create(client, keys, env_id, body, **meta)  # a re-run after completion
    assert done.headers["Location"] == url
    assert done.headers["Upload-Offset"] == str(len(body))
    assert done.headers["Twindelta-Snapshot"] == r.headers["Twindelta-Snapshot"]


def test_a_declared_sha256_that_does_not_match_refuses_the_archive(
    client: TestClient, keys: Keys, sent_tasks: SentTasks
) -> None:
    env_id = make_env(client, keys)
    body = archive()
    url = create(client, keys, env_id, body, sha256="0" * 64).headers["Location"]
    r = patch(client, keys, url, 0, body)
    assert r.status_code == 422 and r.json()["error"] == "ArchiveChecksumMismatch"
    assert sent_tasks.names() == []


def test_wrong_offset_is_409_and_nothing_is_written(client: TestClient, keys: Keys) -> None:
    env_id = make_env(client, keys)
    body = archive()
    url = create(client, keys, env_id, body).headers["Location"]
    r = patch(client, keys, url, 5, body[5:50])
    assert r.status_code == 409 and r.json()["error"] == "OffsetMismatch"
    assert r.headers["Tus-Resumable"] == "1.0.0"
    assert head(client, keys, url).headers["Upload-Offset"] == "0"


def test_checksum_mismatch_is_460_and_the_chunk_is_discarded(
    client: TestClient, keys: Keys
) -> None:
    env_id = make_env(client, keys)
    body = archive()
    url = create(client, keys, env_id, body).headers["Location"]
    assert patch(client, keys, url, 0, body[:10]).status_code == 204
    wrong = base64.b64encode(hashlib.sha1(b"other bytes").digest()).decode()
    r = patch(client, keys, url, 10, body[10:40], **{"Upload-Checksum": f"sha1 {wrong}"})
    assert r.status_code == 460 and r.json()["error"] == "ChecksumMismatch"
    assert head(client, keys, url).headers["Upload-Offset"] == "10"
    r = patch(client, keys, url, 10, body[10:40], **{"Upload-Checksum": "crc99 AAAA"})
    assert r.status_code == 400 and r.json()["error"] == "UnsupportedChecksumAlgorithm"
    right = base64.b64encode(hashlib.sha256(body[10:40]).digest()).decode()
    r = patch(client, keys, url, 10, body[10:40], **{"Upload-Checksum": f"sha256 {right}"})
    assert r.status_code == 204 and r.headers["Upload-Offset"] == "40"


def test_wrong_or_missing_version_is_412(client: TestClient, keys: Keys) -> None:
    env_id = make_env(client, keys)
    headers = {
        **keys.headers("capture"),
        "Upload-Length": "10",
        "Upload-Metadata": metadata(environment_id=env_id, filename="a.zip"),
    }
    for version in ({}, {"Tus-Resumable": "0.2.2"}):
        r = client.post("/v1/uploads", headers={**headers, **version})
        assert r.status_code == 412
        assert r.headers["Tus-Version"] == "1.0.0"
        assert r.json()["error"] == "UnsupportedTusVersion"
    url = create(client, keys, env_id, b"0123456789").headers["Location"]
    r = client.patch(
        url,
        content=b"01",
        headers={**keys.headers("capture"), "Content-Type": OCTETS["Content-Type"],
                 "Upload-Offset": "0"},
    )  # fmt: skip
    assert r.status_code == 412


def test_too_large_is_413(client: TestClient, keys: Keys, monkeypatch: pytest.MonkeyPatch) -> None:
    env_id = make_env(client, keys)
    set_limits(monkeypatch, max_upload_bytes=1000, max_upload_chunk_bytes=100)
    r = create(client, keys, env_id, b"x" * 1001)
    assert r.status_code == 413 and "max_upload_bytes" in r.json()["detail"]
    url = create(client, keys, env_id, b"x" * 500).headers["Location"]
    r = patch(client, keys, url, 0, b"x" * 101)  # one chunk over max_upload_chunk_bytes
    assert r.status_code == 413 and "max_upload_chunk_bytes" in r.json()["detail"]
    assert r.headers["Tus-Resumable"] == "1.0.0"
    small = create(client, keys, env_id, b"x" * 50).headers["Location"]
    r = patch(client, keys, small, 0, b"x" * 60)  # past Upload-Length
    assert r.status_code == 413 and "Upload-Length" in r.json()["detail"]
    assert head(client, keys, small).headers["Upload-Offset"] == "0"


def test_unknown_and_expired_uploads_are_404(
    client: TestClient, keys: Keys, session_factory: sessionmaker[Session]
) -> None:
    env_id = make_env(client, keys)
    assert head(client, keys, "/v1/uploads/nope").status_code == 404
    r = patch(client, keys, "/v1/uploads/nope", 0, b"abc")
    assert r.status_code == 404 and r.json()["error"] == "NotFound"
    url = create(client, keys, env_id, b"x" * 10).headers["Location"]
    with session_factory.begin() as s:
        row = s.get(ResumableUpload, url.rsplit("/", 1)[1])
        assert row is not None
        row.expires_at = utcnow() - timedelta(seconds=1)
    assert head(client, keys, url).status_code == 404
    r = patch(client, keys, url, 0, b"x")
    assert r.status_code == 404 and r.json()["error"] == "UploadExpired"


def test_wrong_content_type_is_415(client: TestClient, keys: Keys) -> None:
    env_id = make_env(client, keys)
    url = create(client, keys, env_id, b"x" * 10).headers["Location"]
    r = client.patch(
        url,
        content=b"xx",
        headers={**keys.headers("capture"), **TUS, "Upload-Offset": "0",
                 "Content-Type": "application/octet-stream"},
    )  # fmt: skip
    assert r.status_code == 415
    r = create(client, keys, env_id, b"x" * 10, filename="photo.jpg")
    assert r.status_code == 415 and r.json()["error"] == "UnsupportedFileType"


def test_bad_metadata_and_headers_are_4xx_naming_them(client: TestClient, keys: Keys) -> None:
    env_id = make_env(client, keys)
    base = {**keys.headers("capture"), **TUS, "Upload-Length": "10"}
    r = client.post("/v1/uploads", headers={**base, "Upload-Metadata": "filename !!!"})
    assert r.status_code == 400 and "filename" in r.json()["detail"]
    r = client.post("/v1/uploads", headers={**base, "Upload-Metadata": metadata(filename="a.zip")})
    assert r.status_code == 422 and "environment_id" in r.json()["detail"]
    meta = metadata(environment_id=env_id, filename="a.zip")
    r = client.post(
        "/v1/uploads", headers={**base, "Upload-Length": "ten", "Upload-Metadata": meta}
    )
    assert r.status_code == 400 and "Upload-Length" in r.json()["detail"]
    r = create(client, keys, "no-such-env", b"x")
    assert r.status_code == 404


def test_bad_archive_answers_the_single_uploads_error_and_is_removed(
    client: TestClient, keys: Keys, sent_tasks: SentTasks, data_dir: Path
) -> None:
    env_id = make_env(client, keys)
    body = b"PK\x03\x04 this is not a zip at all" * 10
    url = create(client, keys, env_id, body).headers["Location"]
    r = patch(client, keys, url, 0, body)
    assert r.status_code == 422 and r.json()["error"] == "InvalidArchive"
    assert sent_tasks.names() == []
    upload_id = url.rsplit("/", 1)[1]
    assert not (data_dir / "files" / "uploads" / upload_id).exists()
    info = client.get(url, headers=keys.headers("capture")).json()
    assert info["state"] == "failed" and info["error"]["code"] == "InvalidArchive"
    r = head(client, keys, url)
    assert r.status_code == 422 and r.headers["Twindelta-Error"] == "InvalidArchive"
    r = patch(client, keys, url, len(body), b"")  # asked again: the same answer
    assert r.status_code == 422 and r.json()["error"] == "InvalidArchive"


def new_upload(
    client: TestClient, keys: Keys, session_factory: sessionmaker[Session], body: bytes
) -> tuple[str, ResumableUpload]:
    """An upload of ``body`` to a new environment: its URL and row."""
    url = create(client, keys, make_env(client, keys), body).headers["Location"]
    with session_factory() as s:
        return url, uploads.get(s, url.rsplit("/", 1)[1])


def part_sizes(folder: Path) -> list[int]:
    """The sizes of the stored parts in an upload's folder, in order (no spool files)."""
    return [p.stat().st_size for p in sorted(folder.iterdir()) if not p.name.startswith(".")]


def test_termination_deletes_the_bytes(client: TestClient, keys: Keys, data_dir: Path) -> None:
    env_id = make_env(client, keys)
    url = create(client, keys, env_id, b"x" * 10).headers["Location"]
    assert patch(client, keys, url, 0, b"x" * 4).status_code == 204
    assert patch(client, keys, url, 4, b"x" * 3).status_code == 204
    partial = data_dir / "files" / "uploads" / url.rsplit("/", 1)[1]
    assert part_sizes(partial) == [4, 3]
    r = client.delete(url, headers={**keys.headers("capture"), **TUS})
    assert r.status_code == 204 and r.headers["Tus-Resumable"] == "1.0.0"
    assert not partial.exists()
    assert head(client, keys, url).status_code == 404


def test_a_key_limited_to_another_environment_sees_404(
    client: TestClient, keys: Keys, session_factory: sessionmaker[Session]
) -> None:
    from app.core import auth

    env_a, env_b = make_env(client, keys, "a"), make_env(client, keys, "b")
    with session_factory.begin() as s:
        _row, token = auth.create_key(s, "station b", ["capture"], environment_ids=[env_b])
    other = {"Authorization": f"Bearer {token}", **TUS}
    r = client.post(
        "/v1/uploads",
        headers={**other, "Upload-Length": "10",
                 "Upload-Metadata": metadata(environment_id=env_a, filename="a.zip")},
    )  # fmt: skip
    assert r.status_code == 404
    url = create(client, keys, env_a, b"x" * 10).headers["Location"]
    assert client.head(url, headers=other).status_code == 404
    assert client.get(url, headers=other).status_code == 404
    r = client.post("/v1/uploads", headers={**TUS, "Upload-Length": "1"})
    assert r.status_code == 401 and r.headers["Tus-Resumable"] == "1.0.0"
    r = create(client, keys, env_a, b"x" * 10, which="read")
    assert r.status_code == 403


def test_an_upload_being_ingested_is_423_until_its_heartbeat_stops(
    client: TestClient,
    keys: Keys,
    sent_tasks: SentTasks,
    session_factory: sessionmaker[Session],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Another request (on any host) claimed the complete upload and beats: a PATCH at its
    full offset and a DELETE answer 423; once its heartbeat is FINISH_STALE_S old (the
    request died), the next PATCH takes over and makes the snapshot."""
    from app.core import ingest
    from app.core.enums import UploadState

    env_id = make_env(client, keys)
    body = archive()
    url = create(client, keys, env_id, body).headers["Location"]
    upload_id = url.rsplit("/", 1)[1]
    with monkeypatch.context() as m, pytest.raises(RuntimeError):
        m.setattr(ingest, "create_snapshot", _killed)
        patch(client, keys, url, 0, body)
    with session_factory.begin() as s:
        row = s.get(ResumableUpload, upload_id)
        assert row is not None and row.state == UploadState.receiving
        row.state, row.heartbeat_at = UploadState.processing, utcnow()
    r = patch(client, keys, url, len(body), b"")
    assert r.status_code == 423 and r.json()["error"] == "UploadLocked"
    assert client.delete(url, headers={**keys.headers("capture"), **TUS}).status_code == 423
    assert head(client, keys, url).headers["Upload-Offset"] == str(len(body))
    with session_factory.begin() as s:
        row = s.get(ResumableUpload, upload_id)
        assert row is not None
        row.heartbeat_at = utcnow() - timedelta(seconds=uploads.FINISH_STALE_S + 1)
    r = patch(client, keys, url, len(body), b"")
    assert r.status_code == 204 and "Twindelta-Snapshot" in r.headers
    assert sent_tasks.names() == ["snapshot.process"]


@pytest.mark.parametrize("parts_left", [True, False], ids=["reads-on", "parts-gone"])
def test_a_stalled_finisher_that_was_taken_over_records_nothing(
    parts_left: bool,
    client: TestClient,
    keys: Keys,
    session_factory: sessionmaker[Session],
    data_dir: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The finishing request stalls past FINISH_STALE_S before its snapshot; another takes
    over and finishes. When the first resumes, it answers with the upload as the other
    recorded it, one snapshot in all: whether it still reads the parts (its host's copies,
    with S3) and its own snapshot is rolled back, or finds them deleted."""
    from app.core import ingest

    body = archive()
    _, row = new_upload(client, keys, session_factory, body)
    storage = LocalStorage(data_dir / "files")
    receiver = spooled(storage, row, 0, body)
    receiver.store(session_factory, get_settings())
    receiver.close()
    real, taken_over = ingest.create_snapshot, []

    def stalled(*args: object, **kwargs: object) -> object:
        if not taken_over:  # the first finisher, before its snapshot: it stalls here
            taken_over.append(None)
            with session_factory.begin() as s:
                stale = s.get(ResumableUpload, row.id)
                assert stale is not None
                stale.heartbeat_at = utcnow() - timedelta(seconds=uploads.FINISH_STALE_S + 1)
            with monkeypatch.context() as m:
                if parts_left:
                    m.setattr(uploads.retention, "delete_after_commit", lambda *_: None)
                taken_over[0] = uploads.finish(
                    session_factory, session_factory, storage, get_settings(), row.id
                )
        return real(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(ingest, "create_snapshot", stalled)
    first = uploads.finish(session_factory, session_factory, storage, get_settings(), row.id)
    second = taken_over[0]
    assert second is not None and second.snapshot_id is not None
    assert first.state == second.state == "completed"
    assert first.snapshot_id == second.snapshot_id and first.job_id == second.job_id
    with session_factory() as s:
        env_snapshots = select(func.count()).select_from(Snapshot)
        assert s.scalar(env_snapshots.where(Snapshot.environment_id == row.environment_id)) == 1


def _killed(*args: object, **kwargs: object) -> object:
    raise RuntimeError("the request died while ingesting")


def test_two_patches_at_one_offset_the_second_stored_is_409_and_leaves_nothing(
    client: TestClient,
    keys: Keys,
    sent_tasks: SentTasks,
    session_factory: sessionmaker[Session],
    data_dir: Path,
) -> None:
    """Both read offset 0 and spool their bodies; the first stored moves the offset, the
    other is 409 OffsetMismatch and its part is deleted; the upload completes from there."""
    body = archive()
    url, row = new_upload(client, keys, session_factory, body)
    upload_id = row.id
    storage = LocalStorage(data_dir / "files")
    first = spooled(storage, row, 0, body[:100])
    second = spooled(storage, row, 0, b"\0" * 300)
    assert first.store(session_factory, get_settings()).offset_bytes == 100
    with pytest.raises(Conflict) as lost:
        second.store(session_factory, get_settings())
    assert lost.value.code == "OffsetMismatch"
    first.close()
    second.close()
    folder = data_dir / "files" / "uploads" / upload_id
    assert part_sizes(folder) == [100] and sorted(p.name for p in folder.iterdir()) == [first.name]
    assert head(client, keys, url).headers["Upload-Offset"] == "100"
    assert patch(client, keys, url, 0, body[:100]).status_code == 409
    r = patch(client, keys, url, 100, body[100:])
    assert r.status_code == 204 and "Twindelta-Snapshot" in r.headers
    snap = client.get(
        f"/v1/snapshots/{r.headers['Twindelta-Snapshot']}", headers=keys.headers("admin")
    ).json()
    assert snap["n_images"] == 3


def test_a_request_killed_mid_body_leaves_the_offset_and_its_spool_is_swept(
    client: TestClient,
    keys: Keys,
    sent_tasks: SentTasks,
    session_factory: sessionmaker[Session],
    data_dir: Path,
) -> None:
    """A killed PATCH leaves only its spool file: the offset does not move, the retry at the
    same offset completes the upload, and the sweep removes the spool once old."""
    body = archive()
    url, row = new_upload(client, keys, session_factory, body)
    assert patch(client, keys, url, 0, body[:50]).status_code == 204
    storage = LocalStorage(data_dir / "files")
    killed = spooled(storage, row, 50, body[50:200])
    killed.fh.flush()  # the process dies here: never stored, never closed
    assert killed.path.stat().st_size == 150
    assert head(client, keys, url).headers["Upload-Offset"] == "50"
    with session_factory.begin() as s:
        counts = uploads.expire(s, storage, orphan_age_s=0, now=utcnow() + timedelta(seconds=1))
    assert counts == {"uploads_expired": 0, "uploads_orphaned": 1}
    assert not killed.path.exists()
    killed.fh.close()
    r = patch(client, keys, url, 50, body[50:])
    assert r.status_code == 204 and "Twindelta-Snapshot" in r.headers


def test_expiry_deletes_expired_uploads_and_orphans(
    client: TestClient, keys: Keys, session_factory: sessionmaker[Session], data_dir: Path
) -> None:
    env_id = make_env(client, keys)
    old_url = create(client, keys, env_id, b"x" * 10).headers["Location"]
    new_url = create(client, keys, env_id, b"x" * 10).headers["Location"]
    assert patch(client, keys, old_url, 0, b"x" * 3).status_code == 204
    assert patch(client, keys, new_url, 0, b"x" * 3).status_code == 204
    folder = data_dir / "files" / "uploads"
    orphan = folder / "no-row"
    orphan.mkdir()
    (orphan / f"{0:020d}.0123456789abcdef").write_bytes(b"left by a deleted upload")
    old_id, new_id = old_url.rsplit("/", 1)[1], new_url.rsplit("/", 1)[1]
    with session_factory.begin() as s:
        row = s.get(ResumableUpload, old_id)
        assert row is not None
        row.expires_at = utcnow() - timedelta(seconds=1)
    storage = LocalStorage(data_dir / "files")
    with session_factory.begin() as s:  # a young orphan stays
        assert uploads.expire(s, storage, orphan_age_s=3600) == {
            "uploads_expired": 1,
            "uploads_orphaned": 0,
        }
    assert not (folder / old_id).exists() and (folder / new_id).exists() and orphan.exists()
    with session_factory.begin() as s:
        assert s.get(ResumableUpload, old_id) is None
        counts = uploads.expire(s, storage, orphan_age_s=0, now=utcnow() + timedelta(seconds=1))
    assert counts == {"uploads_expired": 0, "uploads_orphaned": 1}
    assert not orphan.exists() and (folder / new_id).exists()


def test_a_patch_moves_the_expiry(
    client: TestClient, keys: Keys, session_factory: sessionmaker[Session]
) -> None:
    env_id = make_env(client, keys)
    url = create(client, keys, env_id, b"x" * 10).headers["Location"]
    with session_factory.begin() as s:
        row = s.get(ResumableUpload, url.rsplit("/", 1)[1])
        assert row is not None
        row.expires_at = utcnow() + timedelta(seconds=5)
    r = patch(client, keys, url, 0, b"xx")
    with session_factory() as s:
        row = s.get(ResumableUpload, url.rsplit("/", 1)[1])
        assert row is not None
        assert row.expires_at > utcnow() + timedelta(seconds=get_settings().upload_expiry_s - 60)
    assert r.headers["Upload-Expires"].endswith("GMT")


def test_beat_runs_the_expiry_task_and_it_deletes_expired_uploads(
    client: TestClient, keys: Keys, session_factory: sessionmaker[Session], data_dir: Path
) -> None:
    from app.core import queue
    from workers.maintenance_tasks import expire_uploads

    settings = get_settings()
    entry = next(
        e
        for e in queue.celery_config(settings)["beat_schedule"].values()
        if e["task"] == "maintenance.uploads"
    )
    assert entry["schedule"] == settings.upload_sweep_interval_s
    assert queue.TASK_QUEUES["maintenance.uploads"] == queue.TASK_QUEUES["maintenance.sweep"]
    env_id = make_env(client, keys)
    url = create(client, keys, env_id, b"x" * 10).headers["Location"]
    assert patch(client, keys, url, 0, b"x" * 3).status_code == 204
    upload_id = url.rsplit("/", 1)[1]
    with session_factory.begin() as s:
        row = s.get(ResumableUpload, upload_id)
        assert row is not None
        row.expires_at = utcnow() - timedelta(seconds=1)
    assert expire_uploads() == {"uploads_expired": 1, "uploads_orphaned": 0}
    assert not (data_dir / "files" / "uploads" / upload_id).exists()
    with session_factory() as s:
        assert s.get(ResumableUpload, upload_id) is None


def test_an_unexpected_error_at_the_end_keeps_the_bytes_for_a_retry(
    client: TestClient, keys: Keys, sent_tasks: SentTasks, monkeypatch: pytest.MonkeyPatch
) -> None:
    from app.core import ingest

    env_id = make_env(client, keys)
    body = archive()
    url = create(client, keys, env_id, body).headers["Location"]
    real = ingest.create_snapshot

    def broken(*args: object, **kwargs: object) -> object:
        raise RuntimeError("the database went away")

    monkeypatch.setattr(ingest, "create_snapshot", broken)
    with pytest.raises(RuntimeError):
        patch(client, keys, url, 0, body)
    info = client.get(url, headers=keys.headers("capture")).json()
    assert (info["state"], info["offset"]) == ("receiving", len(body))
    monkeypatch.setattr(ingest, "create_snapshot", real)
    r = patch(client, keys, url, len(body), b"")  # the last PATCH again, with no bytes
    assert r.status_code == 204 and "Twindelta-Snapshot" in r.headers
    assert sent_tasks.names() == ["snapshot.process"]


def test_a_patch_that_loses_the_race_to_the_last_byte_gets_the_final_answer(
    client: TestClient, keys: Keys, sent_tasks: SentTasks, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Read while receiving; when its (empty) chunk is stored the upload has ended."""
    from app.api.routes import uploads as route
    from app.core.enums import UploadState

    env_id = make_env(client, keys)
    body = archive()
    url = create(client, keys, env_id, body).headers["Location"]
    done = patch(client, keys, url, 0, body)
    real = route._load
    calls: list[int] = []

    def stale(key: object, upload_id: str) -> ResumableUpload:
        upload = real(key, upload_id)  # type: ignore[arg-type]
        calls.append(1)
        if len(calls) == 1:
            upload.state = UploadState.receiving  # as it was a moment earlier
        return upload

    monkeypatch.setattr(route, "_load", stale)
    r = patch(client, keys, url, len(body), b"")
    assert r.status_code == 204 and len(calls) == 1
    assert r.headers["Twindelta-Snapshot"] == done.headers["Twindelta-Snapshot"]
