"""Two API processes on one PostgreSQL database: a key revoked through one is refused by the
other on its very next request (no per-process cache of valid keys)."""

from __future__ import annotations

import time
from collections.abc import Callable

import httpx
import pytest

from tests.e2e.conftest import ADMIN_KEY, Processes, api_client, free_port

pytestmark = [pytest.mark.slow, pytest.mark.e2e]


def start_api(procs: Processes, name: str) -> httpx.Client:
    port = free_port()
    procs.api(port, name)
    return api_client(port)


def test_revoke_in_one_process_refused_by_the_other_at_once(
    pg_url: str, processes: Callable[..., Processes]
) -> None:
    procs = processes(database_url=pg_url)
    # one after the other: the first creates the bootstrap admin key
    first = start_api(procs, "api-1")
    second = start_api(procs, "api-2")
    created = first.post("/v1/keys", json={"name": "station", "scopes": ["read"]})
    assert created.status_code == 201, created.text
    station = {"Authorization": f"Bearer {created.json()['key']}"}
    # the second process has just accepted the key (a cache would now hold it)
    for _ in range(3):
        assert second.get("/v1/environments", headers=station).status_code == 200

    revoked = first.delete(f"/v1/keys/{created.json()['id']}")
    assert revoked.status_code == 200, revoked.text
    t0 = time.monotonic()
    r = second.get("/v1/environments", headers=station)
    assert r.status_code == 401, f"the other process still accepted the key: {r.status_code}"
    assert time.monotonic() - t0 < 1.0
    # and the admin key (not revoked) still works in both
    assert first.get("/v1/keys").status_code == 200
    assert second.get("/v1/keys", headers={"Authorization": f"Bearer {ADMIN_KEY}"}).is_success
