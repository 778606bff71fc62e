"""An upload on the embedded default (SQLite) holds the database's write lock only for its
insert, not while its files are staged and checked: another writer (a new API key) gets
through while the upload is being validated."""

from __future__ import annotations

import sqlite3
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from app.core import auth, db, ingest
from app.core.settings import get_settings
from app.main import create_app
from tests.app.api.test_snapshots_upload import CLASSES, as_parts, capture
from tests.app.conftest import SentTasks, migrate


@pytest.fixture
def sqlite_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, sent_tasks: SentTasks
) -> Iterator[Path]:
    """A private migrated SQLite file used the way production uses it: the process's own
    engine and session factories (no test transaction holding the lock)."""
    path = tmp_path / "twindelta.db"
    url = f"sqlite:///{path}"
    migrate(url)
    monkeypatch.setenv("TWINDELTA_DATA_DIR", str(tmp_path))
    monkeypatch.setenv("TWINDELTA_DATABASE_URL", url)
    get_settings.cache_clear()
    db.get_engine.cache_clear()
    monkeypatch.setattr(db, "_session_factory", None)
    monkeypatch.setattr(db, "_read_session_factory", None)
    db.use_session_factory(None)
    yield path
    db.get_engine().dispose()
    db.get_engine.cache_clear()
    get_settings.cache_clear()


def test_upload_validation_does_not_hold_the_write_lock(
    sqlite_file: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    with db.get_session_factory().begin() as s:
        _, token = auth.create_key(s, "admin", ["admin"])
    headers = {"Authorization": f"Bearer {token}"}
    waits: list[float | str] = []
    real_validate = ingest.upload._validate

    def validate_while_another_process_writes(*args: Any, **kwargs: Any) -> Any:
        # What a concurrent POST /v1/keys from another connection does: take the write lock.
        other = sqlite3.connect(sqlite_file, timeout=0.5, isolation_level=None)
        started = time.monotonic()
        try:
            other.execute("BEGIN IMMEDIATE")
            other.execute("ROLLBACK")
            waits.append(time.monotonic() - started)
        except sqlite3.OperationalError as exc:
            waits.append(str(exc))
        finally:
            other.close()
        return real_validate(*args, **kwargs)

    monkeypatch.setattr(ingest.upload, "_validate", validate_while_another_process_writes)
    with TestClient(create_app()) as client:
        env = client.post(
            "/v1/environments", json={"name": "l", "classes": CLASSES}, headers=headers
        )
        assert env.status_code == 201, env.text
        r = client.post(
            f"/v1/environments/{env.json()['id']}/snapshots",
            files=as_parts(capture()),
            headers=headers,
        )
        assert r.status_code == 202, r.text
        snap = client.get(f"/v1/snapshots/{r.json()['snapshot']['id']}", headers=headers)
        assert snap.status_code == 200 and snap.json()["n_images"] == 3
    assert len(waits) == 1
    assert isinstance(waits[0], float) and waits[0] < 0.25, waits


def test_object_upload_does_not_hold_the_write_lock_while_storing(
    sqlite_file: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from app.core.storage import LocalStorage

    with db.get_session_factory().begin() as s:
        _, token = auth.create_key(s, "admin", ["admin"])
    waits: list[float | str] = []
    real_write = LocalStorage.write_stream

    def write_while_another_process_writes(self: LocalStorage, *args: Any, **kw: Any) -> Any:
        other = sqlite3.connect(sqlite_file, timeout=0.5, isolation_level=None)
        started = time.monotonic()
        try:
            other.execute("BEGIN IMMEDIATE")
            other.execute("ROLLBACK")
            waits.append(time.monotonic() - started)
        except sqlite3.OperationalError as exc:
            waits.append(str(exc))
        finally:
            other.close()
        return real_write(self, *args, **kw)

    monkeypatch.setattr(LocalStorage, "write_stream", write_while_another_process_writes)
    ply = b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
    ply += b"property float z\nend_header\n0 0 0\n1 0 0\n0 1 0\n"
    with TestClient(create_app()) as client:
        r = client.post(
            "/v1/objects",
            files={"file": ("m.ply", ply, "application/octet-stream")},
            data={"name": "drill"},
            headers={"Authorization": f"Bearer {token}"},
        )
        assert r.status_code == 202, r.text
        again = client.post(
            "/v1/objects",
            files={"file": ("m.ply", ply, "application/octet-stream")},
            data={"name": "drill"},
            headers={"Authorization": f"Bearer {token}"},
        )
        assert (again.status_code, again.json()["error"]) == (409, "ObjectExists"), again.text
    assert isinstance(waits[0], float) and waits[0] < 0.25, waits
    stored = sorted(
        p.parent.name for p in (sqlite_file.parent / "files" / "objects").rglob("*.ply")
    )
    assert len(stored) == 1  # the refused duplicate left no file
