"""The HTTP client the demo, the benchmarks and the e2e tests share (:mod:`app.client`),
against a fake service (httpx.MockTransport): no server, no database."""

from __future__ import annotations

import json
import tarfile
from pathlib import Path

import httpx
import pytest

from app.client import (
    ApiError,
    Client,
    capture_parts,
    check,
    pack_capture,
    poll_job,
    upload_capture,
)


def capture(tmp_path: Path, cameras: bool) -> Path:
    for sub, names in (("images", ["b.jpg", "a.jpg"]), ("labels", ["b.txt", "a.txt"])):
        (tmp_path / sub).mkdir()
        for name in names:
            (tmp_path / sub / name).write_bytes(name.encode())
    if cameras:
        (tmp_path / "cameras.json").write_text("{}")
    return tmp_path


@pytest.mark.parametrize("cameras", [False, True])
def test_capture_parts_are_images_then_labels_then_cameras_sorted(
    tmp_path: Path, cameras: bool
) -> None:
    parts = [
        (field, path.relative_to(tmp_path).as_posix())
        for field, path in capture_parts(capture(tmp_path, cameras))
    ]
    expected = [
        ("images", "images/a.jpg"),
        ("images", "images/b.jpg"),
        ("detections", "labels/a.txt"),
        ("detections", "labels/b.txt"),
    ]
    assert parts == ([*expected, ("cameras", "cameras.json")] if cameras else expected)


def test_check_returns_the_body_or_raises_with_method_path_and_status() -> None:
    request = httpx.Request("GET", "http://svc/v1/jobs/x")
    assert check(httpx.Response(200, json={"a": 1}, request=request), 200) == {"a": 1}
    with pytest.raises(RuntimeError, match=r"GET /v1/jobs/x: 404 .*NotFound"):
        check(httpx.Response(404, json={"error": "NotFound"}, request=request), 200, 202)


def test_upload_sends_every_part_with_the_idempotency_key(tmp_path: Path) -> None:
    seen: list[httpx.Request] = []

    def service(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        return httpx.Response(202, json={"snapshot": {"id": "s"}, "job": {"id": "j"}})

    with httpx.Client(base_url="http://svc", transport=httpx.MockTransport(service)) as client:
        body = upload_capture(client, "env-1", capture(tmp_path, True), idempotency_key="k-1")
    assert body["job"]["id"] == "j"
    [request] = seen
    assert request.url.path == "/v1/environments/env-1/snapshots"
    assert request.headers["Idempotency-Key"] == "k-1"
    content = request.read()
    for name in (b'name="images"; filename="a.jpg"', b'name="detections"; filename="b.txt"'):
        assert name in content
    assert b'name="cameras"; filename="cameras.json"' in content


def test_poll_job_returns_the_job_once_it_is_final(capsys: pytest.CaptureFixture[str]) -> None:
    states = iter(["queued", "running", "succeeded"])

    def service(request: httpx.Request) -> httpx.Response:
        state = next(states)
        progress = 1.0 if state == "succeeded" else 0.5
        job = {"id": "j", "state": state, "progress": progress, "stage": None}
        return httpx.Response(200, content=json.dumps(job))

    with httpx.Client(base_url="http://svc", transport=httpx.MockTransport(service)) as client:
        job = poll_job(client, "j", "reconstruct")
    assert job["state"] == "succeeded"
    assert "100.0%  succeeded" in capsys.readouterr().out


# --- the typed client ---------------------------------------------------------------------


def test_pack_capture_is_deterministic_and_finds_only_capture_files(tmp_path: Path) -> None:
    (tmp_path / "c").mkdir()
    folder = capture(tmp_path / "c", cameras=True)
    (folder / ".DS_Store").write_bytes(b"junk")
    (folder / "notes.md").write_text("not part of a capture")
    first = pack_capture(folder, tmp_path / "1.tar")
    second = pack_capture(folder, tmp_path / "2.tar")
    assert (first.sha256, first.idempotency_key) == (second.sha256, second.idempotency_key)
    assert (first.n_images, first.n_labels, first.has_cameras) == (2, 2, True)
    with tarfile.open(first.path) as tar:
        assert sorted(tar.getnames()) == [
            "cameras.json",
            "images/a.jpg",
            "images/b.jpg",
            "labels/a.txt",
            "labels/b.txt",
        ]
    (folder / "labels" / "a.txt").write_bytes(b"0 0.5 0.5 0.1 0.1\n")
    assert pack_capture(folder, tmp_path / "3.tar").sha256 != first.sha256
    with pytest.raises(ValueError, match="no images"):
        pack_capture(tmp_path / "c" / "labels", tmp_path / "4.tar")


def test_requests_are_retried_with_doubling_backoff_then_give_up() -> None:
    answers = iter([503, 503, 200])

    def service(request: httpx.Request) -> httpx.Response:
        return httpx.Response(next(answers), json=[{"id": "e1", "name": "cell"}])

    client = Client("http://svc", "k", transport=httpx.MockTransport(service), backoff_s=0.5)
    waits: list[float] = []
    client.sleep = waits.append
    assert client.environment("cell")["id"] == "e1"
    assert waits == [0.5, 1.0]

    def down(request: httpx.Request) -> httpx.Response:
        raise httpx.ConnectError("refused", request=request)

    client = Client("http://svc", "k", transport=httpx.MockTransport(down), retries=3)
    client.sleep = waits.append
    with pytest.raises(ApiError) as caught:
        client.environments()
    assert caught.value.status == 0 and caught.value.code == "ConnectError"

    def refuse(request: httpx.Request) -> httpx.Response:
        return httpx.Response(403, json={"error": "Forbidden", "detail": "needs read"})

    client = Client("http://svc", "k", transport=httpx.MockTransport(refuse))
    with pytest.raises(ApiError, match="403 Forbidden: needs read"):
        client.environments()  # a 4xx is not retried


class FakeTus:
    """An in-memory tus server whose first PATCH takes half its bytes, then drops."""

    def __init__(self) -> None:
        self.received = bytearray()
        self.patches = 0
        self.length = 0

    def __call__(self, request: httpx.Request) -> httpx.Response:
        if request.method == "POST":
            self.length = int(request.headers["Upload-Length"])
            return httpx.Response(201, headers={"Location": "/v1/uploads/u1"})
        if request.method == "HEAD":
            return httpx.Response(200, headers={"Upload-Offset": str(len(self.received))})
        assert int(request.headers["Upload-Offset"]) == len(self.received)
        self.patches += 1
        body = b"".join(request.stream)  # type: ignore[union-attr]
        if self.patches == 1:
            self.received += body[: len(body) // 2]
            raise httpx.ReadError("connection reset", request=request)
        self.received += body
        headers = {"Upload-Offset": str(len(self.received))}
        if len(self.received) == self.length:
            headers |= {"Twindelta-Snapshot": "s1", "Twindelta-Job": "j1"}
        return httpx.Response(204, headers=headers)


def test_upload_resumes_from_the_offset_after_a_dropped_connection(tmp_path: Path) -> None:
    archive = tmp_path / "capture.tar"
    archive.write_bytes(bytes(range(256)) * 400)
    server = FakeTus()
    client = Client("http://svc", "k", transport=httpx.MockTransport(server))
    client.sleep = lambda _s: None
    seen: list[int] = []
    result = client.upload("e1", archive, chunk_bytes=40_000, on_bytes=lambda o, _n: seen.append(o))
    assert bytes(server.received) == archive.read_bytes()
    assert (result.snapshot, result.job, result.resumes) == ("s1", "j1", 1)
    # progress from 0 to the end, back to the resume point (half the first chunk) once
    assert (seen[0], seen[-1]) == (0, archive.stat().st_size)
    assert 20_000 in seen[seen.index(40_000) :]


@pytest.mark.parametrize(
    ("snapshot", "twin_status", "expected"),
    [
        ({"comparison": "c1", "twin_update": None}, "current", "c1"),
        ({"comparison": None, "twin_update": "baseline"}, "current", None),
        ({"comparison": None, "twin_update": None}, "blocked", "TwinBlocked"),
    ],
)
def test_outcome_is_the_comparison_none_for_a_baseline_or_says_the_twin_is_blocked(
    snapshot: dict[str, object], twin_status: str, expected: str | None
) -> None:
    def service(request: httpx.Request) -> httpx.Response:
        path = request.url.path
        if path == "/v1/snapshots/s1":
            return httpx.Response(
                200, json={"state": "reconstructed", "environment": "e1", **snapshot}
            )
        if path == "/v1/comparisons/c1":
            return httpx.Response(200, json={"id": "c1", "job": "j2", "state": "succeeded"})
        if path == "/v1/jobs/j2":
            return httpx.Response(200, json={"state": "succeeded"})
        assert path == "/v1/environments/e1"
        return httpx.Response(200, json={"twin": {"status": twin_status, "comparison": "c0"}})

    client = Client("http://svc", "k", transport=httpx.MockTransport(service))
    if expected == "TwinBlocked":
        with pytest.raises(
            ApiError, match=r"TwinBlocked: comparison c0 failed .* /v1/comparisons/c0/retry"
        ):
            client.outcome("s1")
        return
    found = client.outcome("s1")
    assert (found["id"] if found else None) == expected
