"""Strict JSON request bodies: an ASGI middleware that reads a JSON body once with
:func:`app.core.jsondoc.loads` before FastAPI parses it, and answers 422 naming the field for
what Python's parser lets through or fails on without a useful error (NaN, Infinity, 1e400,
integers past 64 bits or 4,300 digits, nesting deeper than 32 levels, NUL characters and
unpaired surrogates in strings). A body that passes is handed on unchanged. A path or query
with a NUL character is refused too (PostgreSQL cannot compare an id holding one)."""

from __future__ import annotations

import email.message

from fastapi.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app.core import jsondoc
from app.core.errors import InvalidInput


def _is_json(scope: Scope) -> bool:
    """The same rule FastAPI uses to decide a body is JSON: application/json or */*+json."""
    for name, value in scope.get("headers", ()):
        if name == b"content-type":
            message = email.message.Message()
            message["content-type"] = value.decode("latin-1")
            subtype = message.get_content_subtype()
            return message.get_content_maintype() == "application" and (
                subtype == "json" or subtype.endswith("+json")
            )
    return False


async def _reject(scope: Scope, receive: Receive, send: Send, exc: InvalidInput) -> None:
    response = JSONResponse(
        status_code=exc.status_code, content={"error": exc.code, "detail": exc.detail}
    )
    await response(scope, receive, send)


class JsonGuard:
    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        query = scope.get("query_string", b"")
        if "\x00" in scope.get("path", "") or b"%00" in query or b"\x00" in query:
            # PostgreSQL refuses NUL in text: an id with one would be a 500 at the lookup.
            await _reject(scope, receive, send, InvalidInput("path or query: a NUL character"))
            return
        if not _is_json(scope):
            await self.app(scope, receive, send)
            return
        messages: list[Message] = []
        body = bytearray()
        while True:
            message = await receive()
            messages.append(message)
            if message["type"] != "http.request":
                break
            body += message.get("body", b"")
            if not message.get("more_body", False):
                break
        if body.strip():
            try:
                jsondoc.loads(bytes(body), "body")
            except InvalidInput as exc:
                await _reject(scope, receive, send, exc)
                return

        async def replay() -> Message:
            return messages.pop(0) if messages else await receive()

        await self.app(scope, replay, send)
