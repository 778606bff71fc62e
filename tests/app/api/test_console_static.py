"""The console's files at /ui/ (TWINDELTA_CONSOLE_DIR), and the 503 page until it is built."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from app.core.settings import get_settings
from app.main import create_app


@pytest.fixture
def console_client(
    data_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> Iterator[tuple[TestClient, Path]]:
    folder = tmp_path / "dist"
    folder.mkdir()
    monkeypatch.setenv("TWINDELTA_CONSOLE_DIR", str(folder))
    get_settings.cache_clear()
    with TestClient(create_app()) as client:
        yield client, folder


def test_the_built_console_is_served_same_origin(
    console_client: tuple[TestClient, Path],
) -> None:
    client, folder = console_client
    (folder / "index.html").write_text("<!doctype html><title>twindelta</title>")
    (folder / "assets").mkdir()
    (folder / "assets" / "index-abc123.js").write_text("console.log('twin')")
    r = client.get("/ui/")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    assert "<title>twindelta</title>" in r.text
    r = client.get("/ui/assets/index-abc123.js")
    assert r.status_code == 200 and "javascript" in r.headers["content-type"]
    assert r.text == "console.log('twin')"
    assert (
        client.get("/ui", follow_redirects=True).text == r"<!doctype html><title>twindelta</title>"
    )
    assert client.get("/ui/assets/nope.js").status_code == 404
    # nothing outside the folder
    (folder.parent / "secret.txt").write_text("no")
    assert client.get("/ui/../secret.txt").status_code == 404
    assert client.get("/ui/%2e%2e/secret.txt").status_code == 404
    # the API is unchanged beside it
    assert client.get("/v1/environments").status_code == 401


def test_an_unbuilt_console_says_to_run_make_console(
    console_client: tuple[TestClient, Path],
) -> None:
    client, folder = console_client
    for path in ("/ui/", "/ui/assets/index.js"):
        r = client.get(path)
        assert r.status_code == 503 and r.headers["content-type"].startswith("text/html")
        assert "make console" in r.text and str(folder) in r.text


def test_the_console_folder_defaults_to_the_repositorys_build(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.delenv("TWINDELTA_CONSOLE_DIR", raising=False)
    get_settings.cache_clear()
    try:
        repo = Path(__file__).resolve().parents[3]
        assert get_settings().resolved_console_dir == repo / "console" / "dist"
    finally:
        get_settings.cache_clear()
