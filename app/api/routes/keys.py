"""API keys (admin): create (the token is shown once), list, revoke."""

from __future__ import annotations

from fastapi import APIRouter, status
from sqlalchemy import select

from app.api.deps import AdminKey, AnyKey, SessionDep
from app.api.schemas.common import ERRORS, TOO_LARGE, ErrorOut
from app.api.schemas.keys import KeyCreate, KeyCreated, KeyCurrent, KeyRead
from app.core import auth
from app.core.enums import Scope
from app.core.errors import NotFound
from app.core.models import ApiKey

router = APIRouter(prefix="/keys", tags=["keys"], responses=ERRORS)


@router.post("", status_code=status.HTTP_201_CREATED, responses=TOO_LARGE)
def create_key(body: KeyCreate, session: SessionDep, _key: AdminKey) -> KeyCreated:
    """Create a key with scopes, optionally limited to environments; the response is the
    only time the token is shown."""
    row, token = auth.create_key(
        session, body.name, [s.value for s in body.scopes], environment_ids=body.environment_ids
    )
    return KeyCreated(**KeyRead.model_validate(row).model_dump(), key=token)


@router.get("")
def list_keys(session: SessionDep, _key: AdminKey) -> list[KeyRead]:
    """Every key, without secrets."""
    rows = session.scalars(select(ApiKey).order_by(ApiKey.created_at)).all()
    return [KeyRead.model_validate(r) for r in rows]


@router.get("/current")
def current_key(key: AnyKey) -> KeyCurrent:
    """The calling key (any scope): its id, name, scopes and environments, so a client can
    tell whether the key is valid and what it may do."""
    return KeyCurrent(
        id=key.key_id,
        name=key.name,
        scopes=[Scope(s) for s in key.scopes],
        environment_ids=None if key.environment_ids is None else list(key.environment_ids),
    )


@router.delete(
    "/{key_id}",
    responses={409: {"model": ErrorOut, "description": "LastAdminKey: the last admin key"}},
)
def revoke_key(key_id: str, session: SessionDep, _key: AdminKey) -> KeyRead:
    """Revoke a key; every API process refuses it from its next request (409 for the last
    admin key)."""
    row = session.get(ApiKey, key_id)
    if row is None:
        raise NotFound(f"key {key_id} not found")
    auth.revoke(session, row)
    return KeyRead.model_validate(row)
