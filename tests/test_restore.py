"""Backup and restore as docs/operations.md describes them, done for real on both databases.

A service with an environment, an uploaded capture (its images recorded by the worker's
ingest stage) and a reconstructed cloud is backed up database first (SQLite: the online
backup API that ``sqlite3 .backup`` uses; PostgreSQL: ``pg_dump -Fc``), then storage (a
copy), while another upload lands in between. The original is destroyed, both are restored
into a fresh data folder (PostgreSQL: ``pg_restore`` into a new, uniquely named database on
the machine's server), and the API must serve the same snapshot, detections and point-cloud
bytes with the same API key; the cleanup removes the upload that came after the database
backup (files without rows).
"""

from __future__ import annotations

import os
import shutil
import sqlite3
import subprocess
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy.engine import make_url
from sqlalchemy.orm import Session, sessionmaker

from app.core import auth, db, ingest, queue, retention, snapshots
from app.core.enums import JobState, SnapshotState
from app.core.models import Job
from app.core.settings import get_settings
from app.core.storage import LocalStorage
from app.main import create_app
from tests.app.api.test_snapshots_upload import as_parts, capture
from tests.app.conftest import create_pg_database, drop_pg_database, migrate

CLOUD = b"ply\nformat binary_little_endian 1.0\nelement vertex 0\nend_header\n" + os.urandom(4096)


@dataclass
class Service:
    """One running service: its settings (data folder, database), session factory, client."""

    data_dir: Path
    url: str
    factory: sessionmaker[Session]
    client: TestClient

    @property
    def storage(self) -> LocalStorage:
        return LocalStorage(self.data_dir / "files")


@pytest.fixture
def use_service(monkeypatch: pytest.MonkeyPatch) -> Iterator[Any]:
    """Point the process at a data folder and database, as its environment would."""
    monkeypatch.setattr(queue, "send_now", lambda name, **kw: None)  # no workers here
    opened: list[Service] = []

    def start(data_dir: Path, url: str) -> Service:
        for service in opened:
            service.client.__exit__(None, None, None)
            service.factory.kw["bind"].dispose()
        opened.clear()
        monkeypatch.setenv("TWINDELTA_DATA_DIR", str(data_dir))
        monkeypatch.setenv("TWINDELTA_DATABASE_URL", url)
        monkeypatch.delenv("TWINDELTA_STORAGE_DIR", raising=False)
        monkeypatch.delenv("TWINDELTA_BROKER_URL", raising=False)
        get_settings.cache_clear()
        factory = sessionmaker(bind=db.make_engine(url), expire_on_commit=False)
        db.use_session_factory(factory)
        client = TestClient(create_app())
        client.__enter__()
        service = Service(data_dir, url, factory, client)
        opened.append(service)
        return service

    yield start
    for service in opened:
        service.client.__exit__(None, None, None)
        service.factory.kw["bind"].dispose()
    db.use_session_factory(None)
    get_settings.cache_clear()


def _populate(service: Service) -> dict[str, Any]:
    """An environment, a capture uploaded over HTTP, and what the worker would record:
    the images re-read from storage, the cloud, the snapshot reconstructed."""
    with service.factory.begin() as s:
        _row, token = auth.create_key(s, "ops", ["admin", "read", "capture"])
    headers = {"Authorization": f"Bearer {token}"}
    r = service.client.post(
        "/v1/environments",
        json={"name": "hall-7", "classes": ["power_drill", "bowl"]},
        headers=headers,
    )
    assert r.status_code == 201, r.text
    env_id = r.json()["id"]
    r = service.client.post(
        f"/v1/environments/{env_id}/snapshots", files=as_parts(capture()), headers=headers
    )
    assert r.status_code == 202, r.text
    snap_id, job_id = r.json()["snapshot"]["id"], r.json()["job"]["id"]
    settings = get_settings()
    with service.factory.begin() as s:
        snap = snapshots.get(s, snap_id)
        records = ingest.read_capture(
            service.storage, snap.storage_prefix, ["power_drill", "bowl"], settings
        )
        ingest.record_images(s, snap_id, records)
        key = f"{snap.storage_prefix}/reconstruction/cloud.ply"
        service.storage.write_bytes(key, CLOUD)
        snap.pointcloud_key = key
        snap.state = SnapshotState.reconstructed
        s.get_one(Job, job_id).state = JobState.succeeded
    return {"env": env_id, "snapshot": snap_id, "headers": headers}


def _observe(service: Service, made: dict[str, Any]) -> dict[str, Any]:
    """What a client sees of the environment and its snapshot."""
    headers, client = made["headers"], service.client
    listed = client.get(f"/v1/environments/{made['env']}/snapshots", headers=headers)
    assert listed.status_code == 200, listed.text
    snap = client.get(f"/v1/snapshots/{made['snapshot']}", headers=headers)
    assert snap.status_code == 200, snap.text
    cloud = client.get(f"/v1/snapshots/{made['snapshot']}/pointcloud", headers=headers)
    assert cloud.status_code == 200, cloud.text
    with service.factory.begin() as s:
        images = {
            image.name: (image.width, image.height, image.detections)
            for image in snapshots.get(s, made["snapshot"]).images
        }
        files = {
            image.name: service.storage.path(image.file_key).read_bytes()
            for image in snapshots.get(s, made["snapshot"]).images
        }
    body = snap.json()
    return {
        "snapshots": [x["id"] for x in listed.json()],
        "state": body["state"],
        "seq": body["seq"],
        "cloud": cloud.content,
        "images": images,
        "image_files": files,
    }


def _late_upload(service: Service, made: dict[str, Any]) -> str:
    """An upload that lands after the database backup and before the storage copy."""
    r = service.client.post(
        f"/v1/environments/{made['env']}/snapshots",
        files=as_parts(capture()),
        headers=made["headers"],
    )
    assert r.status_code == 202, r.text
    return str(r.json()["snapshot"]["id"])


def _copy_storage(source: Service, backup: Path) -> None:
    shutil.copytree(source.data_dir / "files", backup / "files", symlinks=True)


def _check_restored(
    restored: Service, made: dict[str, Any], before: dict[str, Any], late: str
) -> None:
    assert _observe(restored, made) == before
    assert before["state"] == "reconstructed" and before["cloud"] == CLOUD
    assert len(before["images"]) == 3 and any(d for _w, _h, d in before["images"].values())
    # the late upload's files came along without their row: not served, cleaned up
    late_dir = restored.data_dir / "files" / "snapshots" / late
    assert late_dir.is_dir()
    r = restored.client.get(f"/v1/snapshots/{late}", headers=made["headers"])
    assert r.status_code == 404
    with restored.factory.begin() as s:
        counts = retention.cleanup_files(s, restored.storage, max_age_s=0.0)
    assert counts["snapshots"] == 1 and not late_dir.exists()
    assert _observe(restored, made) == before


def test_sqlite_backup_and_restore(tmp_path: Path, use_service: Any) -> None:
    original = tmp_path / "original"
    url = f"sqlite:///{original / 'twindelta.db'}"
    original.mkdir()
    migrate(url)
    service = use_service(original, url)
    made = _populate(service)
    before = _observe(service, made)

    backup = tmp_path / "backup"
    backup.mkdir()
    # 1. the database, with the online backup API (what `sqlite3 db ".backup 'file'"` runs)
    with (
        sqlite3.connect(original / "twindelta.db") as live,
        sqlite3.connect(backup / "twindelta.db") as copy,
    ):
        live.backup(copy)
    late = _late_upload(service, made)
    # 2. then the storage
    _copy_storage(service, backup)

    service.factory.kw["bind"].dispose()
    shutil.rmtree(original)  # nothing of the original is left to lean on

    fresh = tmp_path / "restored"
    fresh.mkdir()
    shutil.copy2(backup / "twindelta.db", fresh / "twindelta.db")
    shutil.copytree(backup / "files", fresh / "files")
    restored_url = f"sqlite:///{fresh / 'twindelta.db'}"
    migrate(restored_url)  # `twindelta migrate`: a no-op at the same release
    restored = use_service(fresh, restored_url)
    _check_restored(restored, made, before, late)


def _pg(*args: str) -> None:
    result = subprocess.run(args, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, f"{args[0]}: {result.stderr}"


def test_postgres_backup_and_restore(tmp_path: Path, use_service: Any) -> None:
    for tool in ("pg_dump", "pg_restore"):
        if shutil.which(tool) is None:
            pytest.fail(f"{tool} is not installed (Debian: apt-get install postgresql-client)")
    source_name = f"twindelta_restore_src_{uuid.uuid4().hex[:8]}"
    target_name = f"twindelta_restore_dst_{uuid.uuid4().hex[:8]}"
    source_url = create_pg_database(source_name)
    try:
        migrate(source_url)
        original = tmp_path / "original"
        original.mkdir()
        service = use_service(original, source_url)
        made = _populate(service)
        before = _observe(service, made)

        backup = tmp_path / "backup"
        backup.mkdir()
        server = make_url(source_url)
        conn = ["-h", server.host or "127.0.0.1", "-p", str(server.port or 5432)]
        conn += ["-U", server.username or "postgres"]
        # 1. the database (a consistent snapshot while the service runs)
        _pg("pg_dump", *conn, "-d", source_name, "-Fc", "-f", str(backup / "twindelta.dump"))
        late = _late_upload(service, made)
        # 2. then the storage
        _copy_storage(service, backup)

        service.factory.kw["bind"].dispose()
        drop_pg_database(source_name)
        shutil.rmtree(original)

        target_url = create_pg_database(target_name)
        _pg(
            "pg_restore",
            *conn,
            "-d",
            target_name,
            "--no-owner",
            "--exit-on-error",
            str(backup / "twindelta.dump"),
        )
        fresh = tmp_path / "restored"
        fresh.mkdir()
        shutil.copytree(backup / "files", fresh / "files")
        migrate(target_url)
        restored = use_service(fresh, target_url)
        _check_restored(restored, made, before, late)
    finally:
        drop_pg_database(source_name)
        drop_pg_database(target_name)
