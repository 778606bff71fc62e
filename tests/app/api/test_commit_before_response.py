"""A 2xx answer means the transaction has committed: the request's session closes before the
response is sent, so what a client created is readable at once. Checked over real HTTP
(uvicorn), where the order is observable; a test client waits for the whole call."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import httpx
import uvicorn
from fastapi import Request
from sqlalchemy.orm import Session

from app.api import deps
from app.main import create_app
from tests.app.conftest import Keys
from tests.e2e.conftest import free_port


def test_commit_happens_before_the_response(session_factory: object, keys: Keys) -> None:
    events: list[str] = []

    def slow_commit(request: Request) -> Iterator[Session]:
        yield from deps.get_session(request)
        time.sleep(0.3)  # a slow commit: the response must still wait for it
        events.append("committed")

    app = create_app()
    app.dependency_overrides[deps.get_session] = slow_commit
    port = free_port()
    server = uvicorn.Server(uvicorn.Config(app, port=port, log_level="error", lifespan="off"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    try:
        while not server.started:
            time.sleep(0.05)
        r = httpx.post(
            f"http://127.0.0.1:{port}/v1/environments",
            json={"name": "e", "classes": ["a"]},
            headers=keys.headers(),
        )
        events.append("responded")
        assert r.status_code == 201, r.text
    finally:
        server.should_exit = True
        thread.join(timeout=10)
    assert events == ["committed", "responded"]
