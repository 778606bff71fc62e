"""The storage contract, run against both backends: the local folder and an S3 bucket on a
loopback emulator (moto, bench/loopback.py). Then what only the S3 backend does: its read
cache, its trimming, its errors."""

from __future__ import annotations

import hashlib
import io
import multiprocessing
import os
import threading
import time
import tracemalloc
import uuid
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import pytest
from pydantic import ValidationError
from sqlalchemy.orm import Session

from app.core import retention
from app.core.errors import InvalidInput
from app.core.settings import Settings
from app.core.storage import PART_BYTES, LocalStorage, S3Storage, Storage, open_storage
from bench import loopback as s3_server

MiB = 1024 * 1024
Spec = tuple[str, ...]  # how a child process opens the same storage (picklable)


def _open(spec: Spec) -> Storage:
    if spec[0] == "local":
        return LocalStorage(Path(spec[1]))
    _, url, endpoint, data_dir = spec
    return open_storage(Settings(storage_url=url, s3_endpoint_url=endpoint, data_dir=data_dir))


@pytest.fixture(params=["local", "s3"])
def spec(request: pytest.FixtureRequest, tmp_path: Path) -> Spec:
    if request.param == "local":
        return ("local", str(tmp_path / "files"))
    url, endpoint = request.getfixturevalue("s3_storage_url")
    return ("s3", url, endpoint, str(tmp_path / "data"))


@pytest.fixture
def storage(spec: Spec) -> Storage:
    return _open(spec)


def _bucket_keys(storage: Storage) -> list[str]:
    assert isinstance(storage, S3Storage)
    return s3_server.object_keys(str(storage.client.meta.endpoint_url), storage.bucket)


class _Zeros(io.RawIOBase):
    """``n`` bytes made as they are read (a stream that cannot seek, like a request body)."""

    def __init__(self, n: int) -> None:
        self.left = n

    def readable(self) -> bool:
        return True

    def read(self, size: int | None = -1) -> bytes:
        size = self.left if size is None or size < 0 else min(size, self.left)
        self.left -= size
        return b"\0" * size


def _write_and_measure(spec: Spec, n_bytes: int, queue: Any) -> None:
    """In a child process (so the emulator's own memory is not counted): write ``n_bytes``
    from a stream; put (size, sha256, peak traced bytes) on ``queue``."""
    storage = _open(spec)
    storage.write_bytes("warm-up", b"x")  # client set-up is not the write's memory
    tracemalloc.start()
    blob = storage.write_stream("big/stream.bin", _Zeros(n_bytes))  # type: ignore[arg-type]
    queue.put((blob.size_bytes, blob.sha256, tracemalloc.get_traced_memory()[1]))


def test_a_streamed_write_never_holds_the_source(spec: Spec) -> None:
    """Peak memory stays far below the 48 MiB source: 1 MiB chunks on disk; one 8 MiB
    multipart part being read and one being sent with S3 (measured about 19 MB, the same
    for 20 MB and 100 MB)."""
    n_bytes = 48 * MiB
    context = multiprocessing.get_context("spawn")
    queue = context.Queue()
    child = context.Process(target=_write_and_measure, args=(spec, n_bytes, queue))
    child.start()
    size, sha256, peak = queue.get(timeout=120)
    child.join(timeout=30)
    assert size == n_bytes and sha256 == hashlib.sha256(b"\0" * n_bytes).hexdigest()
    assert peak < (10 * MiB if spec[0] == "local" else 3 * PART_BYTES)
    digest = hashlib.sha256()
    for chunk in _open(spec).iter_bytes("big/stream.bin"):
        assert len(chunk) <= MiB
        digest.update(chunk)
    assert digest.hexdigest() == sha256


def test_past_max_bytes_nothing_is_left(storage: Storage) -> None:
    with pytest.raises(OverflowError, match="more than"):
        storage.write_stream("objects/o/model.ply", _Zeros(20 * MiB), max_bytes=12 * MiB)  # type: ignore[arg-type]
    assert not storage.exists("objects/o/model.ply")
    if isinstance(storage, LocalStorage):
        assert [p for p in storage.root.rglob("*") if p.is_file()] == []  # no part file
    if isinstance(storage, S3Storage):
        assert _bucket_keys(storage) == []
        assert storage.remove_partial("objects", time.time() + 60) == 0  # aborted at once


def test_local_file_and_local_dir_give_the_stored_bytes(storage: Storage) -> None:
    files = {"images/a.jpg": b"a" * 1000, "images/b.jpg": b"b" * 10, "labels/a.txt": b"0 .5"}
    for rel, data in files.items():
        blob = storage.write_bytes(f"snapshots/s/{rel}", data)
        assert blob.size_bytes == len(data) and blob.sha256 == hashlib.sha256(data).hexdigest()
    assert storage.local_file("snapshots/s/images/a.jpg").read_bytes() == files["images/a.jpg"]
    folder = storage.local_dir("snapshots/s")
    found = {p.relative_to(folder).as_posix(): p.read_bytes() for p in folder.rglob("*")
             if p.is_file()}  # fmt: skip
    assert found == files
    with storage.open("snapshots/s/labels/a.txt") as fh:
        assert fh.read() == b"0 .5"
    assert storage.exists("snapshots/s/images") and storage.exists("snapshots/s/images/b.jpg")
    with pytest.raises(FileNotFoundError):
        storage.local_file("snapshots/s/images/c.jpg")
    with pytest.raises(FileNotFoundError):
        storage.local_file("snapshots/s/images")  # a folder is not a file
    with pytest.raises(FileNotFoundError):
        storage.local_dir("snapshots/t")
    with pytest.raises(FileNotFoundError):
        storage.open("snapshots/s/nothing")
    assert storage.modified_ns("snapshots/s/nothing") is None
    assert storage.folders("snapshots") .keys() == {"s"}  # fmt: skip
    assert storage.folders("snapshots/s").keys() == {"images", "labels"}


def test_move_in_a_folder(storage: Storage) -> None:
    staged = storage.tmp_dir() / "prepared"
    (staged / "views").mkdir(parents=True)
    (staged / "summary.json").write_text("{}")
    (staged / "views" / "0.npy").write_bytes(b"\1" * 5000)
    storage.move_in(staged, "objects/o/prepared")
    assert not staged.exists()
    folder = storage.local_dir("objects/o/prepared")
    assert (folder / "summary.json").read_text() == "{}"
    assert (folder / "views" / "0.npy").read_bytes() == b"\1" * 5000
    if isinstance(storage, S3Storage):
        prefix = storage.prefix
        assert _bucket_keys(storage) == [
            f"{prefix}/objects/o/prepared/summary.json",
            f"{prefix}/objects/o/prepared/views/0.npy",
        ]


def test_delete_prefix_removes_the_objects_and_this_hosts_copies(storage: Storage) -> None:
    for key in ("snapshots/a/images/1.jpg", "snapshots/a/cloud.ply", "snapshots/ab/cloud.ply"):
        storage.write_bytes(key, key.encode())
    cached = storage.local_file("snapshots/a/cloud.ply")
    storage.local_dir("snapshots/a/images")
    work = storage.scratch_path("snapshots/a/partial")
    work.parent.mkdir(parents=True, exist_ok=True)
    work.write_bytes(b"in place")
    storage.delete_prefix("snapshots/a")
    assert not storage.exists("snapshots/a") and not cached.exists() and not work.exists()
    with pytest.raises(FileNotFoundError):
        storage.local_file("snapshots/a/cloud.ply")
    assert storage.local_file("snapshots/ab/cloud.ply").read_bytes() == b"snapshots/ab/cloud.ply"
    storage.delete_prefix("snapshots/a")  # missing is fine
    if isinstance(storage, S3Storage):
        assert _bucket_keys(storage) == [f"{storage.prefix}/snapshots/ab/cloud.ply"]
        assert not (storage.cache / "snapshots" / "a").exists()


def _read_in_threads(spec: Spec, key: str, queue: Any) -> None:
    storage = _open(spec)
    with ThreadPoolExecutor(4) as pool:
        paths = list(pool.map(lambda _: storage.local_file(key), range(4)))
    queue.put([hashlib.sha256(p.read_bytes()).hexdigest() for p in paths])


def test_concurrent_local_file_in_two_processes_is_safe(spec: Spec) -> None:
    data = os.urandom(3 * MiB)
    _open(spec).write_bytes("snapshots/s/reconstruction/cloud.ply", data)
    context = multiprocessing.get_context("spawn")
    queue = context.Queue()
    children = [
        context.Process(
            target=_read_in_threads,
            args=(spec, "snapshots/s/reconstruction/cloud.ply", queue),
        )
        for _ in range(2)
    ]
    for child in children:
        child.start()
    digests = [digest for _ in children for digest in queue.get(timeout=120)]
    for child in children:
        child.join(timeout=30)
    assert digests == [hashlib.sha256(data).hexdigest()] * 8
    storage = _open(spec)
    folder = storage.local_file("snapshots/s/reconstruction/cloud.ply").parent
    assert [p.name for p in folder.iterdir()] == ["cloud.ply"]  # no part file left


@pytest.mark.parametrize("key", ["../escape", "a/../../b", "/etc/passwd", ""])
def test_bad_keys_are_invalid_input(storage: Storage, key: str) -> None:
    calls = [
        lambda: storage.local_file(key),
        lambda: storage.local_dir(key),
        lambda: storage.write_bytes(key, b"x"),
        lambda: storage.exists(key),
        lambda: storage.open(key),
        lambda: storage.delete_prefix(key),
        lambda: storage.scratch_path(key),
        lambda: storage.move_in(storage.tmp_dir(), key),
    ]
    for call in calls:
        with pytest.raises(InvalidInput, match="invalid storage key"):
            call()


# --- the S3 backend only --------------------------------------------------------------------


@pytest.fixture
def s3(s3_storage_url: tuple[str, str], tmp_path: Path) -> Iterator[S3Storage]:
    url, endpoint = s3_storage_url
    storage = _open(("s3", url, endpoint, str(tmp_path / "data")))
    assert isinstance(storage, S3Storage)
    yield storage


def test_the_cache_is_reused_until_the_object_changes(s3: S3Storage) -> None:
    s3.write_bytes("snapshots/s/cameras.json", b"[1]")
    first = s3.local_file("snapshots/s/cameras.json")
    assert first == s3.cache / "snapshots/s/cameras.json"
    inode = first.stat().st_ino
    assert s3.local_file("snapshots/s/cameras.json").stat().st_ino == inode  # not fetched again
    assert s3.cached_file("snapshots/s/cameras.json") == first
    time.sleep(1.1)  # LastModified has whole seconds
    s3.write_bytes("snapshots/s/cameras.json", b"[1, 2]")
    assert s3.cached_file("snapshots/s/cameras.json") is None
    assert s3.local_file("snapshots/s/cameras.json").read_bytes() == b"[1, 2]"


def test_local_dir_drops_copies_of_objects_gone_from_the_bucket(s3: S3Storage) -> None:
    for name in ("a.jpg", "b.jpg"):
        s3.write_bytes(f"snapshots/s/images/{name}", name.encode())
    s3.local_dir("snapshots/s/images")
    s3.client.delete_object(Bucket=s3.bucket, Key=f"{s3.prefix}/snapshots/s/images/b.jpg")
    folder = s3.local_dir("snapshots/s/images")
    assert sorted(p.name for p in folder.iterdir()) == ["a.jpg"]


def test_trim_cache_removes_the_least_recently_used_first(s3: S3Storage) -> None:
    s3.cache_max_bytes = 2500
    for name in ("old", "mid", "new"):
        s3.write_bytes(f"k/{name}", b"x" * 1000)
        s3.local_file(f"k/{name}")
        time.sleep(0.05)
    s3.local_file("k/old")  # used again: now the newest
    assert s3.trim_cache(keep_recent_s=0) == 1000
    assert sorted(p.name for p in (s3.cache / "k").iterdir()) == ["new", "old"]
    assert s3.trim_cache(keep_recent_s=3600) == 0  # all used just now: kept


def test_unfinished_multipart_uploads_are_aborted(s3: S3Storage) -> None:
    started = s3.client.create_multipart_upload(Bucket=s3.bucket, Key=f"{s3.prefix}/objects/o/m")
    # (moto reports every upload as initiated in 2010, so "not old enough" is not testable)
    assert s3.remove_partial("snapshots", time.time() + 1) == 0  # another prefix
    assert s3.remove_partial("objects", time.time() + 1) == 1
    left = s3.client.list_multipart_uploads(Bucket=s3.bucket).get("Uploads", [])
    assert started["UploadId"] not in [u["UploadId"] for u in left]


def test_check_names_an_unreachable_bucket(s3_storage_url: tuple[str, str], tmp_path: Path) -> None:
    _, endpoint = s3_storage_url
    missing = _open(("s3", "s3://no-such-bucket-here", endpoint, str(tmp_path / "d")))
    with pytest.raises(OSError, match="bucket no-such-bucket-here: no such bucket"):
        missing.check()
    unreachable = _open(("s3", "s3://bucket", "http://127.0.0.1:9", str(tmp_path / "e")))
    with pytest.raises(OSError, match="bucket bucket: HEAD bucket"):
        unreachable.check()
    _open(("s3", *s3_storage_url, str(tmp_path / "f"))).check()


@pytest.mark.parametrize(
    ("url", "complaint"),
    [
        ("http://bucket/x", "is not s3://bucket"),
        ("s3://", "is not a bucket name"),
        ("s3://Upper_Case", "is not a bucket name"),
        ("s3://bucket/a/../b", "has an empty, . or .. part"),
    ],
)
def test_an_invalid_storage_url_is_refused_at_startup(url: str, complaint: str) -> None:
    with pytest.raises(ValidationError, match="TWINDELTA_STORAGE_URL") as caught:
        Settings(storage_url=url)
    assert complaint in str(caught.value)


def test_a_blank_storage_url_means_the_local_folder(tmp_path: Path) -> None:
    settings = Settings(storage_url=" ", data_dir=tmp_path)
    assert settings.storage_url is None
    storage = open_storage(settings)
    assert isinstance(storage, LocalStorage) and storage.root == tmp_path.resolve() / "files"


def test_threads_share_one_client(s3_storage_url: tuple[str, str], tmp_path: Path) -> None:
    url, endpoint = s3_storage_url
    settings = Settings(storage_url=url, s3_endpoint_url=endpoint, data_dir=tmp_path)
    seen: list[Storage] = []
    threads = [threading.Thread(target=lambda: seen.append(open_storage(settings)))
               for _ in range(4)]  # fmt: skip
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert all(s is seen[0] for s in seen)


def test_retention_sweeps_orphans_from_the_bucket(s3: S3Storage, session: Session) -> None:
    """cleanup_files against a bucket: folders of snapshots and objects with no row go once
    idle for max_age_s (by LastModified); a killed job's work folder in scratch at once."""
    s3.write_bytes(f"snapshots/{uuid.uuid4()}/images/a.jpg", b"a")
    s3.write_bytes(f"objects/{uuid.uuid4()}/model.ply", b"ply")
    work = s3.scratch_path(f".work/{uuid.uuid4()}")  # of a job with no row
    work.mkdir(parents=True)
    counts = retention.cleanup_files(session, s3, max_age_s=3600)
    assert (counts["snapshots"], counts["objects"], counts["work"]) == (0, 0, 1)  # too new
    assert not work.exists() and len(_bucket_keys(s3)) == 2
    counts = retention.cleanup_files(session, s3, max_age_s=3600, now=time.time() + 7200)
    assert (counts["snapshots"], counts["objects"]) == (1, 1)
    assert _bucket_keys(s3) == []
