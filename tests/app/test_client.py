"""The HTTP client the demo, the benchmarks and the e2e tests share (:mod:`app.client`),
against a fake service (httpx.MockTransport): no server, no database."""

from __future__ import annotations

import json
from pathlib import Path

import httpx
import pytest

from app.client import capture_parts, check, poll_job, upload_capture


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
