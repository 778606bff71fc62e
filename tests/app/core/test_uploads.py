"""Resumable uploads under real concurrency: PATCHes at one offset stored at the same moment
from threads with their own connections (as API hosts would), on PostgreSQL and SQLite
built by the migrations. Exactly one moves the offset; the others are 409 and their parts
are gone."""

from __future__ import annotations

import threading
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest
from sqlalchemy.orm import Session, sessionmaker

from app.core import environments, uploads
from app.core.db import make_engine
from app.core.errors import Conflict
from app.core.models import ResumableUpload
from app.core.settings import Settings
from app.core.storage import LocalStorage, Storage
from tests.app.conftest import create_pg_database, drop_pg_database, migrate

THREADS = 4
ROUNDS = 10


@pytest.fixture(params=["postgres", "sqlite"])
def factory(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[sessionmaker[Session]]:
    """A session factory on a private migrated database (no test transaction around it)."""
    if request.param == "sqlite":
        url, name = f"sqlite:///{tmp_path / 'u.db'}", None
    else:
        name = f"twindelta_uploads_{uuid.uuid4().hex[:8]}"
        url = create_pg_database(name)
    migrate(url)
    engine = make_engine(url)
    yield sessionmaker(bind=engine, expire_on_commit=False)
    engine.dispose()
    if name is not None:
        drop_pg_database(name)


def spooled(
    storage: Storage, upload: ResumableUpload, start: int, chunk: bytes
) -> uploads.Receiver:
    """A PATCH at ``start`` whose body ``chunk`` is spooled and checked but not yet stored:
    where a request is between its last body byte and :meth:`uploads.Receiver.store`."""
    receiver = uploads.Receiver(storage, upload, start, None)
    receiver.open()
    receiver.write(chunk)
    receiver.commit()
    return receiver


def _race(
    factory: sessionmaker[Session], settings: Settings, receivers: list[uploads.Receiver]
) -> dict[int, str]:
    """Store every receiver at once, each from its own thread; ``"stored"`` or the error code
    by index."""
    barrier = threading.Barrier(len(receivers))
    outcome: dict[int, str] = {}

    def store(i: int) -> None:
        barrier.wait()
        try:
            receivers[i].store(factory, settings)
            outcome[i] = "stored"
        except Conflict as exc:
            outcome[i] = exc.code

    threads = [threading.Thread(target=store, args=(i,)) for i in range(len(receivers))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    return outcome


def test_concurrent_patches_at_one_offset_move_it_once(
    factory: sessionmaker[Session], tmp_path: Path
) -> None:
    settings = Settings(data_dir=tmp_path)
    storage = LocalStorage(tmp_path / "files")
    length = ROUNDS * 1000
    with factory.begin() as s:
        env = environments.create(s, "cell", ["drill"], None, None)
        upload, _ = uploads.create(
            s, settings, uploads.NewUpload(env.id, length=length, filename="a.zip")
        )
    start = 0
    expected: list[str] = []
    for n in range(ROUNDS):
        # one spooled chunk per "host", each another size
        receivers = [
            spooled(storage, upload, start, bytes([i]) * 100 * (i + 1)) for i in range(THREADS)
        ]
        outcome = _race(factory, settings, receivers)
        winners = [i for i, what in outcome.items() if what == "stored"]
        assert len(winners) == 1, (n, outcome)
        assert sorted(outcome.values()) == ["OffsetMismatch"] * (THREADS - 1) + ["stored"]
        start += receivers[winners[0]].written
        expected.append(receivers[winners[0]].name)
        with factory() as s:
            row = uploads.get(s, upload.id)
            assert (row.offset_bytes, row.parts) == (start, expected)
        folder = tmp_path / "files" / "uploads" / upload.id
        assert sorted(p.name for p in folder.iterdir()) == sorted(expected)


def test_sweep_spools_removes_only_old_spool_files_of_this_hosts_scratch(tmp_path: Path) -> None:
    """A killed request's spool (untouched past the cut-off) goes; a live request's spool
    and the stored parts stay."""
    import os
    import time

    storage = LocalStorage(tmp_path / "files")
    folder = storage.scratch_path(f"{uploads.FOLDER}/u1")
    folder.mkdir(parents=True)
    dead, live, part = folder / ".a.part", folder / ".b.part", folder / f"{0:020d}.n1"
    for path in (dead, live, part):
        path.write_bytes(b"x" * 10)
    hour_ago = time.time() - 3600
    os.utime(dead, (hour_ago, hour_ago))
    os.utime(part, (hour_ago, hour_ago))
    assert uploads.sweep_spools(storage, time.time() - 60) == 1
    assert not dead.exists() and live.exists() and part.exists()
    assert uploads.sweep_spools(storage, time.time() - 60) == 0
