"""``/metrics`` reports the storage file system's size, used and free bytes."""

from __future__ import annotations

import shutil

from fastapi.testclient import TestClient

from app.core.settings import get_settings
from tests.app.conftest import Keys


def _gauge(text: str, name: str) -> float:
    values = [float(line.split()[1]) for line in text.splitlines() if line.startswith(f"{name} ")]
    assert len(values) == 1, f"{name} not reported once"
    return values[0]


def test_metrics_report_storage_disk_usage(client: TestClient, keys: Keys) -> None:
    r = client.get("/metrics", headers=keys.headers("read"))
    assert r.status_code == 200
    expected = shutil.disk_usage(get_settings().resolved_storage_dir.parent)
    size = _gauge(r.text, "twindelta_storage_size_bytes")
    used = _gauge(r.text, "twindelta_storage_used_bytes")
    free = _gauge(r.text, "twindelta_storage_free_bytes")
    assert size == expected.total
    # other processes write meanwhile: used and free agree within 1 % of the disk
    assert abs(used - expected.used) < 0.01 * size
    assert abs(free - expected.free) < 0.01 * size
    assert 0 < free < size and used + free <= size
    assert "# TYPE twindelta_storage_free_bytes gauge" in r.text
