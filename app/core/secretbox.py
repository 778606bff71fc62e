"""Secrets at rest: what the service must read back (webhook signing secrets) is stored
encrypted, never in plain text.

Fernet (AES-128-CBC with HMAC-SHA256, from ``cryptography``) under a key derived by
HKDF-SHA256 from ``Settings.secret_key``. Several comma-separated keys rotate the key
itself: the first encrypts, each one decrypts (re-encrypt with :func:`reencrypt`).

With no ``secret_key`` (the embedded default; a broker server requires one, see
:class:`~app.core.settings.Settings`) a random key is generated once into
``data_dir/secret.key`` with mode 0600, created atomically so processes starting together
agree on it.
"""

from __future__ import annotations

import base64
import contextlib
import os
import secrets
from functools import lru_cache
from pathlib import Path

from cryptography.fernet import Fernet, InvalidToken, MultiFernet
from cryptography.hazmat.primitives import hashes
from cryptography.hazmat.primitives.kdf.hkdf import HKDF

from app.core.errors import DomainError
from app.core.settings import Settings

KEY_FILE = "secret.key"
_INFO = b"twindelta secrets at rest v1"
TOKEN_PREFIX = "gAAAAA"  # every Fernet token starts so (version byte 0x80, then a timestamp)


class SecretUnreadable(DomainError):
    """A stored secret that no configured key decrypts (the key was changed or lost)."""

    status_code = 500
    code = "SecretUnreadable"


def key_file(settings: Settings) -> Path:
    return settings.data_dir / KEY_FILE


def _load_or_create_key_file(path: Path) -> str:
    """The generated key: read it, or write a new one (0600) if there is none yet."""
    with contextlib.suppress(FileNotFoundError):
        return path.read_text().strip()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(secrets.token_urlsafe(32) + "\n")
            f.flush()
            os.fsync(f.fileno())
        with contextlib.suppress(FileExistsError):  # another process was first: use its key
            os.link(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path.read_text().strip()


def keys(settings: Settings) -> tuple[str, ...]:
    """The configured keys, newest first (or the generated one)."""
    if settings.secret_key is not None:
        values = settings.secret_key.get_secret_value().split(",")
        return tuple(v.strip() for v in values if v.strip())
    return (_load_or_create_key_file(key_file(settings).resolve()),)


@lru_cache(maxsize=8)
def _box(keys: tuple[str, ...]) -> MultiFernet:
    def fernet(key: str) -> Fernet:
        derived = HKDF(algorithm=hashes.SHA256(), length=32, salt=None, info=_INFO).derive(
            key.encode()
        )
        return Fernet(base64.urlsafe_b64encode(derived))

    return MultiFernet([fernet(k) for k in keys])


def encrypt(settings: Settings, plain: str) -> str:
    """A Fernet token of ``plain`` under the newest key (ASCII, ~2x the plain length + 100)."""
    return _box(keys(settings)).encrypt(plain.encode()).decode("ascii")


def decrypt(settings: Settings, token: str) -> str:
    """The plain text of a token made by :func:`encrypt` with any configured key."""
    try:
        return _box(keys(settings)).decrypt(token.encode("ascii")).decode()
    except (InvalidToken, ValueError) as exc:
        raise SecretUnreadable(
            "a stored secret cannot be decrypted with TWINDELTA_SECRET_KEY (was the key "
            "changed without keeping the old one after a comma?)"
        ) from exc


def reencrypt(settings: Settings, token: str) -> str:
    """``token`` under the newest key (after a key rotation)."""
    try:
        return _box(keys(settings)).rotate(token.encode("ascii")).decode("ascii")
    except (InvalidToken, ValueError) as exc:
        raise SecretUnreadable(
            "a stored secret cannot be decrypted with any key in TWINDELTA_SECRET_KEY"
        ) from exc
