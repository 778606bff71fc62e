"""Settings read from the environment: an empty bootstrap key is no key."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from app.core.settings import Settings


@pytest.mark.parametrize("value", ["", "   "])
def test_empty_bootstrap_admin_key_is_unset(monkeypatch: pytest.MonkeyPatch, value: str) -> None:
    """docker-compose passes ``TWINDELTA_BOOTSTRAP_ADMIN_KEY=`` when the operator set none;
    that must start the service with no bootstrap key, not fail validation."""
    monkeypatch.setenv("TWINDELTA_BOOTSTRAP_ADMIN_KEY", value)
    assert Settings().bootstrap_admin_key is None


def test_short_bootstrap_admin_key_is_still_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("TWINDELTA_BOOTSTRAP_ADMIN_KEY", "short")
    with pytest.raises(ValidationError, match="at least 16 characters"):
        Settings()
    monkeypatch.setenv("TWINDELTA_BOOTSTRAP_ADMIN_KEY", "a-long-enough-admin-key-0123")
    assert Settings().bootstrap_admin_key == "a-long-enough-admin-key-0123"
