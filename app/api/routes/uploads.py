"""Resumable uploads: the tus 1.0 protocol (core, creation, termination, checksum,
expiration) under ``/v1/uploads`` for one capture archive, which becomes a snapshot through
the same ingest as ``POST /v1/environments/{id}/snapshots`` (app/core/uploads.py)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Header, Request, Response, status
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool
from starlette.requests import ClientDisconnect
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app.api.answers import point_to
from app.api.deps import CaptureKey, SessionDep, SettingsDep, StorageDep
from app.api.schemas.common import ERRORS, ErrorOut, conflict
from app.api.schemas.uploads import UploadRead
from app.core import auth, uploads
from app.core.auth import Principal
from app.core.db import get_read_session_factory, get_session_factory
from app.core.enums import UploadState
from app.core.errors import Conflict, DomainError, PayloadTooLarge, UnsupportedMedia
from app.core.models import ResumableUpload

router = APIRouter(tags=["uploads"], responses=ERRORS)

OFFSET_CONTENT_TYPE = "application/offset+octet-stream"
# Bytes gathered from the request body before one write to the spool file.
WRITE_BYTES = 1024 * 1024

_TUS = {"Tus-Resumable": {"schema": {"type": "string", "enum": [uploads.TUS_VERSION]}}}
_VERSION: dict[int | str, dict[str, Any]] = {
    412: {
        "model": ErrorOut,
        "description": "Tus-Resumable missing or not 1.0.0 (Tus-Version names what is spoken)",
    }
}
_OFFSET = {"Upload-Offset": {"schema": {"type": "integer"}, "description": "bytes received"}}
_RESULT = {
    "Twindelta-Snapshot": {"schema": {"type": "string"}, "description": "once complete"},
    "Twindelta-Job": {"schema": {"type": "string"}, "description": "once complete"},
}
TusVersion = Annotated[
    str | None, Header(alias="Tus-Resumable", description="the protocol version: 1.0.0")
]


class TusHeaders:
    """ASGI middleware for ``/v1/uploads``: ``Tus-Resumable: 1.0.0`` on every answer
    (errors of the key and size checks too), and 412 with ``Tus-Version`` for a tus request
    (POST, HEAD, PATCH, DELETE) whose ``Tus-Resumable`` is missing or another version."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        path = scope.get("path", "")
        if scope["type"] != "http" or not (
            path == "/v1/uploads" or path.startswith("/v1/uploads/")
        ):
            await self.app(scope, receive, send)
            return
        tus_method = scope["method"] in (
            {"POST"} if path == "/v1/uploads" else {"HEAD", "PATCH", "DELETE"}
        )
        version = next((v for k, v in scope["headers"] if k.lower() == b"tus-resumable"), None)
        if tus_method and version != uploads.TUS_VERSION.encode():
            await _precondition_failed(send, version)
            return

        async def send_with_version(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = [h for h in message.get("headers", []) if h[0] != b"tus-resumable"]
                headers.append((b"tus-resumable", uploads.TUS_VERSION.encode()))
                message = {**message, "headers": headers}
            await send(message)

        await self.app(scope, receive, send_with_version)


async def _precondition_failed(send: Send, version: bytes | None) -> None:
    said = repr(version.decode(errors="replace")) if version is not None else "missing"
    detail = f"Tus-Resumable: {said}; this server speaks {uploads.TUS_VERSION}"
    body = json.dumps({"error": "UnsupportedTusVersion", "detail": detail}).encode()
    await send(
        {
            "type": "http.response.start",
            "status": 412,
            "headers": [
                (b"content-type", b"application/json"),
                (b"content-length", str(len(body)).encode()),
                (b"tus-version", uploads.TUS_VERSION.encode()),
                (b"tus-resumable", uploads.TUS_VERSION.encode()),
            ],
        }
    )
    await send({"type": "http.response.body", "body": body})


def _reachable(session: Session, key: Principal, upload_id: str) -> ResumableUpload:
    """The upload, 404 (word for word the unknown id's) when the key cannot reach its
    environment, or past its expiry."""
    upload = uploads.get(session, upload_id)
    auth.require_environment(key, upload.environment_id, detail=f"upload {upload_id} not found")
    return upload


def _result_headers(upload: ResumableUpload, response: Response) -> None:
    if upload.snapshot_id and upload.job_id:
        response.headers["Twindelta-Snapshot"] = upload.snapshot_id
        response.headers["Twindelta-Job"] = upload.job_id


@router.options(
    "/uploads",
    status_code=status.HTTP_204_NO_CONTENT,
    response_class=Response,
    responses={
        204: {
            "description": "what this tus server supports",
            "headers": {
                "Tus-Version": {"schema": {"type": "string"}},
                "Tus-Extension": {"schema": {"type": "string"}},
                "Tus-Max-Size": {"schema": {"type": "integer"}},
                "Tus-Checksum-Algorithm": {"schema": {"type": "string"}},
            },
        }
    },
)
def upload_options(settings: SettingsDep, key: CaptureKey) -> Response:
    """tus discovery: version, extensions, the largest upload and the checksum algorithms."""
    return Response(
        status_code=status.HTTP_204_NO_CONTENT,
        headers={
            "Tus-Version": uploads.TUS_VERSION,
            "Tus-Extension": uploads.TUS_EXTENSIONS,
            "Tus-Max-Size": str(settings.max_upload_bytes),
            "Tus-Checksum-Algorithm": ",".join(uploads.CHECKSUMS),
        },
    )


@router.post(
    "/uploads",
    status_code=status.HTTP_201_CREATED,
    response_class=Response,
    responses={
        201: {
            "description": "created (or, for the same idempotency_key, sha256 and length, the "
            "unexpired upload that already exists: Idempotent-Replayed: true)",
            "headers": {
                "Location": {"schema": {"type": "string"}},
                "Upload-Expires": {"schema": {"type": "string"}},
                **_OFFSET,
                **_TUS,
            },
        },
        400: {"model": ErrorOut, "description": "Upload-Length or Upload-Metadata malformed"},
        413: {"model": ErrorOut, "description": "Upload-Length over max_upload_bytes"},
        415: {"model": ErrorOut, "description": "filename is not .zip, .tar or .tar.gz"},
        **_VERSION,
    },
)
def create_upload(
    session: SessionDep,
    settings: SettingsDep,
    key: CaptureKey,
    tus_resumable: TusVersion,
    upload_length: Annotated[
        str | None, Header(alias="Upload-Length", description="the archive's size, bytes")
    ] = None,
    upload_metadata: Annotated[
        str | None,
        Header(
            alias="Upload-Metadata",
            description="comma-separated `key base64(value)`: environment_id, filename "
            "(.zip, .tar, .tar.gz), optional idempotency_key and sha256 (hex, of the archive)",
        ),
    ] = None,
) -> Response:
    """tus creation: a new upload of one capture archive (201 + Location)."""
    new = uploads.NewUpload.from_headers(upload_length, upload_metadata)
    auth.require_environment(key, new.environment_id)
    upload, created = uploads.create(session, settings, new)
    response = Response(status_code=status.HTTP_201_CREATED)
    point_to(response, f"/v1/uploads/{upload.id}", replayed=not created)
    response.headers["Upload-Expires"] = uploads.expires_header(upload.expires_at)
    response.headers["Upload-Offset"] = str(uploads.offset(upload))
    if not created:
        _result_headers(upload, response)
    return response


@router.head(
    "/uploads/{upload_id}",
    response_class=Response,
    responses={
        200: {
            "description": "the offset to resume from; the snapshot and job once complete",
            "headers": {
                **_OFFSET,
                "Upload-Length": {"schema": {"type": "integer"}},
                "Upload-Expires": {"schema": {"type": "string"}},
                "Cache-Control": {"schema": {"type": "string"}},
                **_RESULT,
                **_TUS,
            },
        },
        409: {"description": "the archive was refused (this is its status; GET says why)"},
        413: {"description": "the archive was refused (this is its status; GET says why)"},
        415: {"description": "the archive was refused (this is its status; GET says why)"},
        **_VERSION,
    },
)
def head_upload(upload_id: str, session: SessionDep, key: CaptureKey, tus: TusVersion) -> Response:
    """tus offset: Upload-Offset and Upload-Length (a refused archive answers its error's
    status, with Twindelta-Error naming it)."""
    upload = _reachable(session, key, upload_id)
    headers = {"Cache-Control": "no-store", "Upload-Length": str(upload.length)}
    if upload.state == UploadState.failed and upload.error_status is not None:
        headers["Twindelta-Error"] = upload.error_code or "InvalidUpload"
        return Response(status_code=upload.error_status, headers=headers)
    response = Response(status_code=status.HTTP_200_OK, headers=headers)
    response.headers["Upload-Offset"] = str(uploads.offset(upload))
    response.headers["Upload-Expires"] = uploads.expires_header(upload.expires_at)
    _result_headers(upload, response)
    return response


@router.get("/uploads/{upload_id}")
def get_upload(upload_id: str, session: SessionDep, key: CaptureKey) -> UploadRead:
    """The upload: offset, state, and the snapshot and job it became (or why it was refused)."""
    upload = _reachable(session, key, upload_id)
    return UploadRead.of(upload, uploads.offset(upload))


@router.delete(
    "/uploads/{upload_id}",
    status_code=status.HTTP_204_NO_CONTENT,
    response_class=Response,
    responses={
        204: {"description": "deleted with its bytes", "headers": _TUS},
        423: {"model": ErrorOut, "description": "its archive is being ingested; retry"},
        **_VERSION,
    },
)
def delete_upload(
    upload_id: str, session: SessionDep, storage: StorageDep, key: CaptureKey, tus: TusVersion
) -> Response:
    """tus termination: the upload and its bytes go (a snapshot it made stays)."""
    upload = _reachable(session, key, upload_id)
    uploads.terminate(session, storage, upload)
    return Response(status_code=status.HTTP_204_NO_CONTENT)


def _load(key: Principal, upload_id: str) -> ResumableUpload:
    with get_read_session_factory()() as session:
        return _reachable(session, key, upload_id)


def _stored_error(upload: ResumableUpload) -> DomainError:
    """The error the archive of a failed upload was refused with, to answer again."""
    error = DomainError(upload.error_detail or "the archive was refused", code=upload.error_code)
    error.status_code = upload.error_status or 422
    return error


@dataclass(frozen=True)
class ChunkHeaders:
    """A PATCH's Upload-Offset and its optional Upload-Checksum, checked."""

    start: int
    checksum: tuple[str, bytes] | None


def chunk_headers(
    tus: TusVersion,
    content_type: Annotated[str | None, Header(alias="Content-Type")] = None,
    upload_offset: Annotated[str | None, Header(alias="Upload-Offset")] = None,
    upload_checksum: Annotated[
        str | None,
        Header(alias="Upload-Checksum", description="`<sha1|sha256|sha512|md5> <base64>`"),
    ] = None,
) -> ChunkHeaders:
    """415 unless the body is ``application/offset+octet-stream``; 400 for a malformed
    Upload-Offset or Upload-Checksum."""
    if (content_type or "").split(";")[0].strip().lower() != OFFSET_CONTENT_TYPE:
        raise UnsupportedMedia(
            f"Content-Type must be {OFFSET_CONTENT_TYPE}", code="UnsupportedMediaType"
        )
    return ChunkHeaders(
        uploads.parse_offset(upload_offset), uploads.parse_checksum(upload_checksum)
    )


async def _receive(request: Request, receiver: uploads.Receiver) -> bool:
    """Stream the request body into ``receiver`` in writes of :data:`WRITE_BYTES`; returns
    whether the client went away (what arrived is kept unless the chunk had a checksum).
    Any error discards the chunk."""
    buffer = bytearray()
    try:
        async for chunk in request.stream():
            buffer += chunk
            if len(buffer) >= WRITE_BYTES:
                await run_in_threadpool(receiver.write, buffer)
                buffer = bytearray()
        if buffer:
            await run_in_threadpool(receiver.write, buffer)
    except ClientDisconnect:
        if buffer:
            await run_in_threadpool(receiver.write, buffer)
        await run_in_threadpool(receiver.keep_partial)
        return True
    except BaseException:
        await run_in_threadpool(receiver.rollback)
        raise
    await run_in_threadpool(receiver.commit)
    return False


@router.patch(
    "/uploads/{upload_id}",
    status_code=status.HTTP_204_NO_CONTENT,
    response_class=Response,
    openapi_extra={
        "requestBody": {
            "required": True,
            "content": {OFFSET_CONTENT_TYPE: {"schema": {"type": "string", "format": "binary"}}},
        }
    },
    responses={
        204: {
            "description": "the bytes are stored; after the last one the archive is a "
            "snapshot (Twindelta-Snapshot, Twindelta-Job, Location: the job)",
            "headers": {
                **_OFFSET,
                "Upload-Expires": {"schema": {"type": "string"}},
                "Location": {"schema": {"type": "string"}, "description": "once complete"},
                **_RESULT,
                **_TUS,
            },
        },
        400: {"model": ErrorOut, "description": "Upload-Offset or Upload-Checksum malformed"},
        **conflict(
            "OffsetMismatch: Upload-Offset is not the upload's offset (HEAD it); or the "
            "archive's Idempotency-Key was used with other files"
        ),
        413: {"model": ErrorOut, "description": "over Upload-Length or the chunk limit"},
        415: {"model": ErrorOut, "description": "Content-Type is not offset+octet-stream"},
        423: {"model": ErrorOut, "description": "its archive is being ingested; retry"},
        460: {"model": ErrorOut, "description": "Upload-Checksum mismatch: chunk discarded"},
        507: {"model": ErrorOut, "description": "storage full"},
        **_VERSION,
    },
)
async def patch_upload(
    upload_id: str,
    request: Request,
    storage: StorageDep,
    settings: SettingsDep,
    key: CaptureKey,
    chunk: Annotated[ChunkHeaders, Depends(chunk_headers)],
) -> Response:
    """tus PATCH: append the body at Upload-Offset; the last byte makes the snapshot."""
    start, checksum = chunk.start, chunk.checksum
    upload = await run_in_threadpool(_load, key, upload_id)
    if upload.state in (UploadState.completed, UploadState.failed):
        return _ended(upload, start)
    uploads.check_offset(upload, start)
    remaining = max(upload.length - start, 0)
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > remaining:
        raise PayloadTooLarge(
            f"Content-Length {declared} runs past Upload-Length ({remaining} bytes left)"
        )
    receiver = uploads.Receiver(storage, upload, start, checksum)
    await run_in_threadpool(receiver.open)
    try:
        dropped = await _receive(request, receiver)
        upload = await run_in_threadpool(receiver.store, get_session_factory(), settings)
    finally:
        await run_in_threadpool(receiver.close)
    if upload.state in (UploadState.completed, UploadState.failed):
        return _ended(upload, start)
    if dropped or upload.offset_bytes < upload.length:  # dropped: nobody reads this answer
        headers = {
            "Upload-Offset": str(upload.offset_bytes),
            "Upload-Expires": uploads.expires_header(upload.expires_at),
        }
        return Response(status_code=status.HTTP_204_NO_CONTENT, headers=headers)
    done = await run_in_threadpool(
        uploads.finish,
        get_session_factory(),
        get_read_session_factory(),
        storage,
        settings,
        upload_id,
    )
    if done.state == UploadState.failed:
        raise _stored_error(done)
    return _final(done)


def _ended(upload: ResumableUpload, start: int) -> Response:
    """The answer for a PATCH to an upload that already ended: its final answer again at
    its full offset, 409 at another; a refused archive's error."""
    if upload.state == UploadState.failed:
        raise _stored_error(upload)
    if start != upload.length:
        raise Conflict(
            f"Upload-Offset {start}: upload {upload.id} is complete ({upload.length} bytes)",
            code="OffsetMismatch",
        )
    return _final(upload)


def _final(upload: ResumableUpload) -> Response:
    response = Response(
        status_code=status.HTTP_204_NO_CONTENT, headers={"Upload-Offset": str(upload.length)}
    )
    _result_headers(upload, response)
    if upload.job_id:
        response.headers["Location"] = f"/v1/jobs/{upload.job_id}"
    return response
