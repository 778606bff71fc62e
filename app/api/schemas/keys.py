from __future__ import annotations

from datetime import datetime

from pydantic import BaseModel, Field

from app.api.schemas.common import Model
from app.core.enums import Scope


class KeyCreate(BaseModel):
    name: str = Field(min_length=1, max_length=200)
    scopes: list[Scope] = Field(min_length=1)
    environment_ids: list[str] | None = Field(
        default=None,
        max_length=1000,
        description="the environments the key reaches (capture and read keys only); "
        "null: every environment",
    )


class KeyRead(Model):
    id: str
    name: str
    prefix: str = Field(description="a non-secret id of the key; generated tokens start with it")
    scopes: list[Scope]
    environment_ids: list[str] | None = Field(
        description="the environments the key reaches; null: every environment"
    )
    created_at: datetime
    revoked_at: datetime | None


class KeyCreated(KeyRead):
    key: str = Field(description="the secret token; shown only in this response")


class KeyCurrent(BaseModel):
    """The calling key: what it may do (``scopes`` as granted; admin implies read, capture
    and metrics, read implies metrics) and where (``environment_ids``, null: every one)."""

    id: str
    name: str
    scopes: list[Scope]
    environment_ids: list[str] | None
