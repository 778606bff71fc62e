"""Request bodies: the API key is checked and the size capped before any body byte is read.

FastAPI parses a request's body (a multipart upload is spooled to temporary files) before
the route's dependencies run, so an API-key dependency alone would answer 401 only after a
stranger's whole upload was on disk. :class:`BodyGuard` is an ASGI middleware in front of
the routes: for a ``/v1`` request that carries a body it

1. answers 401 when the ``Authorization`` key is missing, unknown or revoked (429 while
   the client is over its limit of unknown keys; any valid key passes here, the route's
   dependency still checks the scope and answers 403), and
2. caps the body: a snapshot upload at ``max_upload_bytes``, an object model at
   ``max_file_bytes``, a laser scan at ``max_scan_bytes`` (each plus the multipart
   framing), a resumable upload's PATCH at ``max_upload_chunk_bytes``, everything else
   (JSON) at ``max_json_bytes``. A declared ``Content-Length`` over the cap is a 413
   before reading; a chunked body is counted as it arrives and cut off with a 413 at the cap.

Both answers are ``{"error": code, "detail": text}`` like every other error.
"""

from __future__ import annotations

import json
import re

from starlette.datastructures import Headers
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app.api.deps import authenticate_request, bearer
from app.core.errors import DomainError
from app.core.settings import Settings, get_settings

# Room for the multipart framing: part headers (~200 bytes each) and the form fields.
FRAMING_PER_FILE = 1024
FRAMING_BYTES = 1024**2

_SNAPSHOT_UPLOAD = re.compile(r"^/v1/environments/[^/]+/snapshots/?$")
_OBJECT_UPLOAD = re.compile(r"^/v1/objects/?$")
_SCAN_UPLOAD = re.compile(r"^/v1/environments/[^/]+/scans/?$")
_UPLOAD_CHUNK = re.compile(r"^/v1/uploads/[^/]+/?$")


def body_limit(method: str, path: str, settings: Settings) -> tuple[int, str]:
    """The most bytes a ``method`` request to ``path`` may send, and what the limit is."""
    if method == "POST" and _SNAPSHOT_UPLOAD.match(path):
        cap = settings.max_upload_bytes + settings.max_upload_files * FRAMING_PER_FILE
        return cap + FRAMING_BYTES, f"max_upload_bytes ({settings.max_upload_bytes})"
    if method == "POST" and _SCAN_UPLOAD.match(path):
        return (
            settings.max_scan_bytes + FRAMING_BYTES,
            f"max_scan_bytes ({settings.max_scan_bytes})",
        )
    if method == "POST" and _OBJECT_UPLOAD.match(path):
        return (
            settings.max_file_bytes + FRAMING_BYTES,
            f"max_file_bytes ({settings.max_file_bytes})",
        )
    if method == "PATCH" and _UPLOAD_CHUNK.match(path):  # one tus chunk, no framing
        return (
            settings.max_upload_chunk_bytes,
            f"max_upload_chunk_bytes ({settings.max_upload_chunk_bytes})",
        )
    return settings.max_json_bytes, f"max_json_bytes ({settings.max_json_bytes})"


class _TooLarge(Exception):
    """Raised from ``receive`` when a chunked body passes its cap."""


async def _answer(
    send: Send, status: int, code: str, detail: str, extra: dict[str, str] | None = None
) -> None:
    body = json.dumps({"error": code, "detail": detail}).encode()
    headers = [
        (b"content-type", b"application/json"),
        (b"content-length", str(len(body)).encode()),
        (b"connection", b"close"),
    ]
    headers += [(k.lower().encode(), v.encode()) for k, v in (extra or {}).items()]
    await send({"type": "http.response.start", "status": status, "headers": headers})
    await send({"type": "http.response.body", "body": body})


class BodyGuard:
    """ASGI middleware: authenticate, then cap, every ``/v1`` request that has a body."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or not scope["path"].startswith("/v1/"):
            await self.app(scope, receive, send)
            return
        headers = Headers(scope=scope)
        length_header = headers.get("content-length")
        chunked = "transfer-encoding" in headers
        try:
            length = int(length_header) if length_header is not None else None
        except ValueError:
            await _answer(send, 400, "InvalidInput", "Content-Length is not a number")
            return
        if not chunked and not length:
            await self.app(scope, receive, send)  # no body to protect
            return
        try:
            client = scope["client"][0] if scope.get("client") else "unknown"
            # Any valid key passes (scope None); the route's dependency checks its scope on
            # this principal instead of looking the key up again.
            principal = await authenticate_request(scope["app"], client, bearer(headers), None)
            scope.setdefault("state", {})["principal"] = principal
        except DomainError as exc:  # 401 (or whatever the key check answers, e.g. 429)
            await _answer(send, exc.status_code, exc.code, exc.detail, exc.headers)
            return
        cap, what = body_limit(scope["method"], scope["path"], get_settings())
        detail = f"the request body is larger than {cap} bytes ({what})"
        if length is not None and length > cap:
            await _answer(send, 413, "PayloadTooLarge", detail)
            return
        await self._capped(scope, receive, send, cap, detail)

    async def _capped(
        self, scope: Scope, receive: Receive, send: Send, cap: int, detail: str
    ) -> None:
        received = 0
        over = False
        started = False

        async def counting_receive() -> Message:
            nonlocal received, over
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > cap:
                    over = True
                    raise _TooLarge(detail)
            return message

        async def guarded_send(message: Message) -> None:
            nonlocal started
            if over:  # the app is answering its own parse error: ours replaces it
                if message["type"] == "http.response.start" and not started:
                    started = True
                    await _answer(send, 413, "PayloadTooLarge", detail)
                return
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, counting_receive, guarded_send)
        except _TooLarge:
            if not started:
                await _answer(send, 413, "PayloadTooLarge", detail)
