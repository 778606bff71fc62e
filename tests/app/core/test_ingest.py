"""The ingest service called directly: the worker's re-read (read_capture), idempotent
recording of images (record_images), the shared parsers, and the idempotency race."""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from sqlalchemy import select
from sqlalchemy.orm import Session

from app.core import environments, ingest
from app.core.errors import DomainError
from app.core.models import Snapshot, SnapshotImage
from app.core.settings import get_settings
from app.core.storage import LocalStorage
from tests.app.api.test_snapshots_upload import CLASSES, capture, image_bytes, png_claiming


@pytest.fixture
def storage(data_dir: Path) -> LocalStorage:
    return LocalStorage(get_settings().resolved_storage_dir)


@pytest.fixture
def env_id(session: Session) -> str:
    return environments.create(session, "line-1", CLASSES, None, None).id


def parts(files: dict[str, bytes], suffixes: tuple[str, ...]) -> list[ingest.UploadPart]:
    return [
        ingest.UploadPart(name, io.BytesIO(body))
        for name, body in files.items()
        if name.endswith(suffixes) and name != "cameras.json"
    ]


def store(
    session: Session,
    storage: LocalStorage,
    env_id: str,
    files: dict[str, bytes],
    key: str | None = None,
) -> ingest.Ingested:
    cameras = files.get("cameras.json")
    return ingest.create_snapshot(
        session,
        storage,
        get_settings(),
        env_id,
        ingest.UploadFiles(
            images=parts(files, (".jpg", ".png")),
            detections=parts(files, (".txt",)),
            cameras=ingest.UploadPart("cameras.json", io.BytesIO(cameras)) if cameras else None,
        ),
        idempotency_key=key,
    )


def test_read_capture_and_record_images(
    session: Session, storage: LocalStorage, env_id: str
) -> None:
    files = capture()
    files["a1.jpg"] = image_bytes("JPEG", size=(40, 30), seed=5)
    snap = store(session, storage, env_id, files).snapshot
    settings = get_settings()

    records = ingest.read_capture(storage, snap.storage_prefix, CLASSES, settings)
    assert [r.name for r in records] == ["a0.jpg", "a1.jpg", "a2.png"]
    by_name = {r.name: r for r in records}
    assert (by_name["a0.jpg"].width, by_name["a0.jpg"].height) == (32, 24)
    assert (by_name["a1.jpg"].width, by_name["a1.jpg"].height) == (40, 30)
    assert by_name["a2.png"].size_bytes == len(files["a2.png"])
    assert by_name["a2.png"].labels_key is None and by_name["a2.png"].detections == []
    assert by_name["a0.jpg"].file_key == f"{snap.storage_prefix}/images/a0.jpg"
    assert by_name["a0.jpg"].labels_key == f"{snap.storage_prefix}/labels/a0.txt"
    assert by_name["a0.jpg"].detections == [
        {"class_id": 0, "class": "power_drill", "cx": 0.5, "cy": 0.5, "w": 0.2, "h": 0.3,
         "confidence": None},
        {"class_id": 1, "class": "bowl", "cx": 0.25, "cy": 0.75, "w": 0.1, "h": 0.1,
         "confidence": 0.9},
    ]  # fmt: skip

    ingest.record_images(session, snap.id, records)
    rows = _rows(session, snap.id)
    assert [r.name for r in rows] == ["a0.jpg", "a1.jpg", "a2.png"]
    assert (rows[1].width, rows[1].height, len(rows[1].detections)) == (40, 30, 1)
    assert all(r.verified_at is not None for r in rows)
    ids = [r.id for r in rows]

    # A redelivered task records the same rows again: no duplicates, same ids.
    ingest.record_images(session, snap.id, ingest.read_capture(
        storage, snap.storage_prefix, CLASSES, settings
    ))  # fmt: skip
    assert [r.id for r in _rows(session, snap.id)] == ids
    assert (snap.n_images, snap.n_detections) == (3, 3)

    # The re-read is authoritative: a label file gone and an image gone show in the rows.
    storage.path(f"{snap.storage_prefix}/images/a2.png").unlink()
    storage.path(f"{snap.storage_prefix}/labels/a1.txt").unlink()
    ingest.record_images(
        session, snap.id, ingest.read_capture(storage, snap.storage_prefix, CLASSES, settings)
    )
    rows = _rows(session, snap.id)
    assert [r.name for r in rows] == ["a0.jpg", "a1.jpg"] and rows[1].detections == []
    assert rows[1].labels_key is None
    assert (snap.n_images, snap.n_detections) == (2, 2)


def _rows(session: Session, snapshot_id: str) -> list[SnapshotImage]:
    session.expire_all()
    return list(
        session.scalars(
            select(SnapshotImage)
            .where(SnapshotImage.snapshot_id == snapshot_id)
            .order_by(SnapshotImage.name)
        )
    )


def test_read_capture_rejects_what_upload_rejects(
    session: Session, storage: LocalStorage, env_id: str
) -> None:
    """The worker uses the upload's parsers: damaged files fail with the same codes."""
    snap = store(session, storage, env_id, capture()).snapshot
    prefix = snap.storage_prefix
    storage.write_bytes(f"{prefix}/labels/a0.txt", b"0 0.5 0.5 0.1 0.1\n5 0.5 0.5 0.1 0.1\n")
    with pytest.raises(DomainError) as err:
        ingest.read_capture(storage, prefix, CLASSES, get_settings())
    assert err.value.code == "UnknownClass" and "labels/a0.txt line 2" in err.value.detail
    storage.write_bytes(f"{prefix}/labels/a0.txt", b"1 0.5 0.5 0.1 0.1\n")
    storage.write_bytes(f"{prefix}/images/a1.jpg", image_bytes()[:200])
    with pytest.raises(DomainError) as err:
        ingest.read_capture(storage, prefix, CLASSES, get_settings())
    assert err.value.code == "InvalidImage" and "images/a1.jpg" in err.value.detail
    # Fewer classes than when uploaded: class 1 is now unknown.
    storage.write_bytes(f"{prefix}/images/a1.jpg", image_bytes())
    assert len(ingest.read_capture(storage, prefix, CLASSES, get_settings())) == 3
    with pytest.raises(DomainError) as err:
        ingest.read_capture(storage, prefix, CLASSES[:1], get_settings())
    assert err.value.code == "UnknownClass"


def test_idempotency_race_returns_the_winner(
    session: Session, storage: LocalStorage, env_id: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A concurrent identical request that commits while this one validates wins; this one
    returns its snapshot and job and stores nothing of its own."""
    files = capture()
    validate = ingest.upload._validate
    winner: list[ingest.Ingested] = []

    def racing_validate(staging: Any, classes: Any) -> Any:
        monkeypatch.setattr(ingest.upload, "_validate", validate)
        winner.append(store(session, storage, env_id, files, key="k"))
        return validate(staging, classes)

    monkeypatch.setattr(ingest.upload, "_validate", racing_validate)
    loser = store(session, storage, env_id, files, key="k")
    assert loser.created is False and winner[0].created is True
    assert loser.snapshot.id == winner[0].snapshot.id and loser.job.id == winner[0].job.id
    assert session.scalars(select(Snapshot.id)).all() == [winner[0].snapshot.id]
    assert [p.name for p in storage.path("snapshots").iterdir()] == [winner[0].snapshot.id]


def test_seq_per_environment(session: Session, storage: LocalStorage, env_id: str) -> None:
    other = environments.create(session, "line-2", CLASSES, None, None).id
    seqs = [store(session, storage, e, capture()).snapshot.seq for e in (env_id, other, env_id)]
    assert seqs == [1, 1, 2]


# --- the shared parsers ---------------------------------------------------------------------


def test_parse_detections_formats() -> None:
    text = b"\xef\xbb\xbf0 0.1 0.2 0.3 0.4\r\n\r\n  1   1 0 1 0   0.5  \n1.0 0 0 0 0"
    got = ingest.parse_detections(io.BytesIO(text), "x.txt", CLASSES, 10)
    assert [(d["class"], d["cx"], d["confidence"]) for d in got] == [
        ("power_drill", 0.1, None),
        ("bowl", 1.0, 0.5),
        ("bowl", 0.0, None),
    ]
    long_line = b"0 " + b"0" * 2000 + b"\n"
    with pytest.raises(DomainError, match=r"x\.txt line 1: longer than"):
        ingest.parse_detections(io.BytesIO(long_line), "x.txt", CLASSES, 10)


def test_parse_cameras_per_image_and_errors() -> None:
    intrinsics = {
        "model": "SIMPLE_RADIAL",
        "width": 640,
        "height": 480,
        "params": [500, 320, 240, 0],
    }
    doc = {"intrinsics_per_image": {"a.jpg": intrinsics}, "poses": {"a.jpg": np.eye(4).tolist()}}
    got = ingest.parse_cameras(io.BytesIO(json.dumps(doc).encode()), "cameras.json", {"a.jpg"})
    assert got["intrinsics_per_image"]["a.jpg"]["params"] == [500.0, 320.0, 240.0, 0.0]
    bad: list[tuple[dict[str, Any], str]] = [
        ({}, "give 'intrinsics'"),
        ({"intrinsics": dict(intrinsics, width=0)}, "width must be a positive integer"),
        ({"intrinsics": dict(intrinsics, params=[1, 2, "x", 4])}, "finite numbers"),
        ({"intrinsics_per_image": {"b.jpg": intrinsics}}, "not uploaded: ['b.jpg']"),
        ({"intrinsics": intrinsics, "poses": {"a.jpg": [[1, 0], [0, 1]]}}, "poses['a.jpg']"),
        ({"intrinsics": intrinsics, "extra": 1}, "unknown keys ['extra']"),
    ]
    for body, message in bad:
        with pytest.raises(DomainError) as err:
            ingest.parse_cameras(io.BytesIO(json.dumps(body).encode()), "cameras.json", {"a.jpg"})
        assert err.value.code == "InvalidCameras" and message in err.value.detail, body


def test_probe_image_checks_header_before_decoding() -> None:
    jpeg = image_bytes("JPEG", size=(800, 600))
    assert ingest.probe_image(io.BytesIO(jpeg), "a.jpg", 10**6) == (800, 600)
    with pytest.raises(DomainError) as err:
        ingest.probe_image(io.BytesIO(jpeg), "a.jpg", 800 * 600 - 1)
    assert err.value.code == "ImageTooLarge" and err.value.status_code == 413
    png = image_bytes("PNG", size=(20, 10))
    assert ingest.probe_image(io.BytesIO(png), "a.png", 10**6) == (20, 10)
    corrupt = bytearray(png)
    corrupt[-20] ^= 0xFF  # inside IDAT/IEND: the CRC check or decoding fails
    with pytest.raises(DomainError) as err:
        ingest.probe_image(io.BytesIO(bytes(corrupt)), "a.png", 10**6)
    assert err.value.code == "InvalidImage" and "a.png" in err.value.detail
    # Within the pixel limit, but the pixel stream is shorter than the header promises.
    with pytest.raises(DomainError) as err:
        ingest.probe_image(io.BytesIO(png_claiming(1000, 1000)), "b.png", 10**7)
    assert err.value.code == "InvalidImage" and "b.png: pixel data ends early" in err.value.detail


def test_an_upload_whose_transaction_rolls_back_leaves_no_files(
    session: Session, storage: LocalStorage, env_id: str
) -> None:
    """The files are moved in before the commit; a failed commit (here: a rollback after
    create_snapshot returned) takes them away again, so no folder is left without a row."""
    result = store(session, storage, env_id, capture())
    prefix = result.snapshot.storage_prefix
    assert storage.exists(f"{prefix}/images/a0.jpg")
    session.rollback()
    assert not storage.exists(prefix)
    assert list((storage.root / "snapshots").iterdir()) == []
    staging = storage.root / ".tmp"
    assert not staging.exists() or list(staging.iterdir()) == []


def test_sweep_staging_removes_only_abandoned_folders(storage: LocalStorage) -> None:
    import fcntl
    import os

    base = storage.root / ".tmp"
    base.mkdir(parents=True, exist_ok=True)
    # an upload in progress in another process: its lock is held
    (base / "live").mkdir()
    live = os.open(base / "live.lock", os.O_CREAT | os.O_RDWR)
    fcntl.flock(live, fcntl.LOCK_EX | fcntl.LOCK_NB)
    # an upload whose process died: the folder and its (free) lock file remain
    (base / "dead" / "images").mkdir(parents=True)
    (base / "dead" / "images" / "a.jpg").write_bytes(b"x" * 1000)
    (base / "dead.lock").touch()
    # a fresh folder without a lock (another use of .tmp): left alone
    (base / "probe").mkdir()
    try:
        assert ingest.sweep_staging(storage) == 1
        assert sorted(p.name for p in base.iterdir()) == ["live", "live.lock", "probe"]
    finally:
        os.close(live)
