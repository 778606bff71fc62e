"""The command line's tables."""

from __future__ import annotations

from pathlib import Path

import httpx
import pytest

from app import cli
from app.cli import _state_table
from app.client import Client


def test_the_state_table_shows_seeded_instances_and_their_external_ids() -> None:
    pose = [[1.0, 0, 0, 0.42], [0, 1.0, 0, 1.07], [0, 0, 1.0, 0.8], [0, 0, 0, 1.0]]
    state = {
        "twin": {"snapshot": None, "seq": 0, "status": "current"},
        "objects": [
            {
                "object": "power_drill",
                "pose": pose,
                "since_snapshot": None,  # seeded before any snapshot
                "instance_id": "3f2c",
                "external_id": "urn:plant-7:drill-1",
            },
            {"object": "mug", "pose": None, "since_snapshot": "9c1d", "instance_id": "77aa"},
        ],
    }
    lines = _state_table(state).splitlines()
    assert lines[1].endswith("since snapshot  instance  external id")
    assert lines[2].split() == [
        "power_drill",
        "0.420",
        "1.070",
        "0.800",
        "-",
        "3f2c",
        "urn:plant-7:drill-1",
    ]
    assert lines[3].split() == ["mug", "-", "-", "-", "9c1d", "77aa", "-"]


def test_seed_sends_the_file_once_with_its_content_type_and_names_refusals(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    sent: list[httpx.Request] = []

    def service(request: httpx.Request) -> httpx.Response:
        if request.method == "GET" and request.url.path == "/v1/environments":
            return httpx.Response(200, json=[{"id": "e1", "name": "cell-2"}])
        sent.append(request)
        if b"hammer" in request.content:
            detail = "1 of 1 rows refused, nothing was written: row 0: unknown class 'hammer'"
            return httpx.Response(422, json={"error": "InvalidInput", "detail": detail})
        made = [{"object": "mug", "instance_id": "i1", "external_id": "urn:mug-3"}]
        return httpx.Response(201, json=made)

    def client(url: str, key: str, retries: int) -> Client:
        return Client(url, key, retries=retries, transport=httpx.MockTransport(service))

    monkeypatch.setattr(cli, "Client", client)
    rows = tmp_path / "objects.csv"
    rows.write_text("object,external_id,m00\nmug,urn:mug-3,1\n")
    args = ["seed", str(rows), "--env", "cell-2", "--key", "k", "--url", "http://svc"]
    assert cli.main(args) == 0
    assert capsys.readouterr().out.splitlines() == [
        "seeded 1 instance(s)",
        "mug                  i1  urn:mug-3",
    ]
    [request] = sent
    assert request.url.path == "/v1/environments/e1/objects/import"
    assert request.headers["content-type"] == "text/csv"
    assert request.content == rows.read_bytes()

    bad = tmp_path / "objects.json"
    bad.write_text('[{"object": "hammer", "pose": []}]')
    assert cli.main([*args[:1], str(bad), *args[2:]]) == 1
    assert sent[-1].headers["content-type"] == "application/json" and len(sent) == 2
    assert "row 0: unknown class 'hammer'" in capsys.readouterr().err


def test_upload_names_a_missing_folder_before_asking_the_service(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """No request is made (the URL is unreachable): the folder is the problem named."""
    missing = tmp_path / "no-capture"
    argv = ["upload", str(missing), "--env", "x", "--url", "http://127.0.0.1:9", "--key", "k"]
    assert cli.main(argv) == 1
    assert f"{missing}: no such folder" in capsys.readouterr().err
