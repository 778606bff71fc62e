"""Domain errors. Each carries its HTTP status; one handler renders them as
``{"error": code, "detail": text}``."""

from __future__ import annotations


class DomainError(Exception):
    """Base of every error a caller can act on."""

    status_code: int = 400
    code: str = "BadRequest"
    headers: dict[str, str] | None = None

    def __init__(self, detail: str, *, code: str | None = None) -> None:
        super().__init__(detail)
        self.detail = detail
        if code is not None:
            self.code = code


class InvalidInput(DomainError):
    status_code = 422
    code = "InvalidInput"


class NotFound(DomainError):
    status_code = 404
    code = "NotFound"


class Conflict(DomainError):
    status_code = 409
    code = "Conflict"


class Gone(DomainError):
    """410: the resource existed and was deleted on purpose (e.g. photos by retention)."""

    status_code = 410
    code = "Gone"


class Unauthorized(DomainError):
    status_code = 401
    code = "Unauthorized"


class Forbidden(DomainError):
    status_code = 403
    code = "Forbidden"


class TooManyRequests(DomainError):
    """429 with ``Retry-After``: the caller must wait ``retry_after_s`` seconds."""

    status_code = 429
    code = "TooManyRequests"

    def __init__(self, detail: str, *, retry_after_s: int) -> None:
        super().__init__(detail)
        self.headers = {"Retry-After": str(retry_after_s)}


class PayloadTooLarge(DomainError):
    status_code = 413
    code = "PayloadTooLarge"


class UnsupportedMedia(DomainError):
    status_code = 415
    code = "UnsupportedMediaType"


class InsufficientStorage(DomainError):
    """507: the server's storage is full; nothing of the request was kept, retry later."""

    status_code = 507
    code = "InsufficientStorage"
