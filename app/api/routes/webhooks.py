"""Webhook subscriptions and their delivery log (filled in by the webhooks work)."""

from __future__ import annotations

from fastapi import APIRouter

from app.api.schemas.common import ERRORS

router = APIRouter(prefix="/webhooks", tags=["webhooks"], responses=ERRORS)
