"""Service settings: environment variables prefixed ``TWINDELTA_``.

The embedded default needs none of them: SQLite, a file-system broker and local storage under
``TWINDELTA_DATA_DIR``. Production sets ``TWINDELTA_DATABASE_URL`` (PostgreSQL) and
``TWINDELTA_BROKER_URL`` (Redis).
"""

from __future__ import annotations

import re
from functools import lru_cache
from pathlib import Path

from pydantic import Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    """Every knob of the service; read once per process (see :func:`get_settings`)."""

    model_config = SettingsConfigDict(env_prefix="TWINDELTA_", extra="ignore")

    data_dir: Path = Field(default=Path("twindelta-data"))
    database_url: str | None = None
    broker_url: str | None = None
    storage_dir: Path | None = None
    # Blob storage: unset, every file lives under the local folder ``storage_dir`` (default
    # data_dir/files); ``s3://bucket/optional/prefix``, in an S3-compatible bucket (credentials
    # from the standard AWS environment: AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY, profiles).
    storage_url: str | None = None
    # The S3 API's address for MinIO and other S3-compatible stores (unset: AWS's own).
    s3_endpoint_url: str | None = None
    # The bucket's region (unset: the AWS configuration's default).
    s3_region: str | None = None
    # This host's private folder with S3 storage: upload staging, tus partial files, job work
    # folders and the read cache (default data_dir/scratch; local storage uses its own folder).
    scratch_dir: Path | None = None
    # The read cache in scratch is trimmed, least recently used first, past this many bytes.
    scratch_cache_max_bytes: int = Field(default=20 * 1024**3, gt=0)
    bootstrap_admin_key: str | None = None
    # After this many unknown or revoked API keys from one client address within
    # ``auth_failure_window_s``, that address gets 429 (with Retry-After) for the rest of the
    # window. Counted in each API process; the address is the socket peer, or the one
    # uvicorn takes from X-Forwarded-For with --proxy-headers behind a trusted proxy.
    auth_failure_limit: int = Field(default=20, ge=1)
    auth_failure_window_s: float = Field(default=60.0, gt=0)

    # Ingest limits: a request over any of them gets 413 and leaves nothing behind.
    max_upload_files: int = 2000
    max_upload_bytes: int = 4 * 1024**3
    max_file_bytes: int = 200 * 1024**2
    max_image_pixels: int = 50_000_000
    max_detection_lines: int = 10_000
    min_images: int = 3
    # An image's decoded size (width × height × channels × bytes per sample), checked from
    # its header before anything is decoded: a 16-bit RGBA PNG costs 8 bytes a pixel.
    max_image_decoded_bytes: int = 200_000_000
    # Archives: every member (folders too) counts; an archive may inflate at most this many
    # times its compressed size (JPEG and PNG barely compress; a zip bomb inflates ~1000×).
    max_archive_members: int = 10_000
    max_archive_ratio: float = 100.0
    # Request bodies are capped before they are read: JSON bodies at ``max_json_bytes``,
    # a snapshot upload at ``max_upload_bytes`` and an object model at ``max_file_bytes``
    # (each plus the multipart framing).
    max_json_bytes: int = 2 * 1024**2
    # A laser scan upload (POST /v1/environments/{id}/scans): the file, streamed to storage.
    max_scan_bytes: int = 8 * 1024**3
    # Resumable (tus) uploads under /v1/uploads: one PATCH carries at most
    # ``max_upload_chunk_bytes`` (the whole upload at most ``max_upload_bytes``); an upload
    # not written to for ``upload_expiry_s`` expires and beat's ``maintenance.uploads``
    # (every ``upload_sweep_interval_s``) deletes its bytes and, once expired, its record.
    max_upload_chunk_bytes: int = Field(default=512 * 1024**2, gt=0)
    upload_expiry_s: float = Field(default=24 * 3600.0, gt=0)
    upload_sweep_interval_s: float = Field(default=300.0, gt=0)

    # Jobs: a running job whose heartbeat is older than this is failed by the sweeper; a
    # queued job older than ``requeue_after_s`` is sent again (a lost broker message).
    heartbeat_timeout_s: float = 120.0
    heartbeat_interval_s: float = 10.0
    max_job_attempts: int = 3
    requeue_after_s: float = 120.0
    sweep_interval_s: float = 30.0
    progress_interval_s: float = 2.0
    # A worker retries a database write that failed on a lock or a lost connection (a
    # PostgreSQL restart) for this long; past it the job is left to the sweeper to requeue.
    db_retry_s: float = 120.0
    # GET /v1/jobs/{id} may answer from a per-process cache this young (0 turns it off)
    job_poll_cache_s: float = 0.5
    task_time_limit_s: int = 3 * 3600
    broker_visibility_timeout_s: int = 6 * 3600

    # Webhooks: retry schedule in seconds after each failed attempt (about a day in total).
    webhook_retry_schedule_s: list[float] = Field(
        default=[5, 30, 120, 600, 1800, 3600, 7200, 14400, 28800, 28800]
    )
    # One overall deadline per delivery attempt: lookup, connect, TLS, request, response
    # headers and the 1 KB excerpt (a receiver trickling bytes cannot hold a thread longer).
    webhook_timeout_s: float = Field(default=10.0, gt=0)
    webhook_allowed_networks: list[str] = Field(default_factory=list)
    # After POST /v1/webhooks/{id}/rotate-secret the previous secret stays valid this long:
    # deliveries carry both signatures until then (0: the old secret stops at once).
    webhook_secret_overlap_s: float = Field(default=24 * 3600.0, ge=0)

    # Secrets at rest (webhook signing secrets) are encrypted with a key derived from this
    # value: 32+ characters, e.g. `openssl rand -hex 32`. To change it, give the new and the
    # old comma-separated (the first encrypts, each decrypts). Unset in the embedded default:
    # a key is generated into ``data_dir/secret.key`` (mode 0600) on first use. Required
    # with a broker server (TWINDELTA_BROKER_URL): processes on other machines share no
    # data_dir, so a generated key would differ between them.
    secret_key: SecretStr | None = None

    # Retention (app/core/retention.py), run every ``retention_interval_s`` by beat; 0 turns
    # a rule off. Photos of snapshots older than ``retention_images_after_days`` are deleted
    # (clouds, cameras and detections stay); only the newest ``retention_keep_last_snapshots``
    # snapshots of each environment are kept (never the newest reconstructed one). Work
    # folders of finished jobs go at once; upload staging and orphaned files left by killed
    # processes once older than ``stale_files_after_s``.
    retention_images_after_days: float = Field(default=0.0, ge=0, le=36_500)
    retention_keep_last_snapshots: int = Field(default=0, ge=0)
    retention_interval_s: float = Field(default=3600.0, gt=0)
    stale_files_after_s: float = Field(default=24 * 3600.0, gt=0)

    # The operator console's built files, served at /ui/ (make console builds them); default
    # the repository's console/dist.
    console_dir: Path | None = None

    @field_validator("secret_key")
    @classmethod
    def _refuse_placeholder_secret_key(cls, value: SecretStr | None) -> SecretStr | None:
        if value is None or not value.get_secret_value().strip():
            return None  # ``KEY=`` means unset
        for key in value.get_secret_value().split(","):
            key = key.strip()
            if len(key) < 32 or len(set(key)) < 8 or "change" in key.lower():
                raise ValueError(
                    "TWINDELTA_SECRET_KEY: each key must be 32+ random characters, not a "
                    "placeholder (e.g. `openssl rand -hex 32`)"
                )
        return value

    @field_validator("storage_url", "s3_endpoint_url", "s3_region")
    @classmethod
    def _blank_is_unset(cls, value: str | None) -> str | None:
        if value is None or not value.strip():
            return None  # ``NAME=`` (docker-compose's default when unset) means unset
        return value.strip()

    @field_validator("storage_url")
    @classmethod
    def _check_storage_url(cls, value: str | None) -> str | None:
        if value is not None:
            parse_s3_url(value)
        return value

    @model_validator(mode="after")
    def _require_secret_key_with_a_broker_server(self) -> Settings:
        if self.secret_key is None and self.broker_url:
            raise ValueError(
                "TWINDELTA_SECRET_KEY is required with TWINDELTA_BROKER_URL (it encrypts "
                "webhook secrets at rest and every process must share it), e.g. "
                "`openssl rand -hex 32`"
            )
        return self

    @field_validator("bootstrap_admin_key")
    @classmethod
    def _refuse_weak_key(cls, value: str | None) -> str | None:
        if value is not None and not value.strip():
            return None  # ``KEY=`` (docker-compose's default when unset) means no key
        if value is not None and (len(value) < 16 or value.lower() in {"changeme", "change-me"}):
            raise ValueError("TWINDELTA_BOOTSTRAP_ADMIN_KEY must be at least 16 characters")
        return value

    @property
    def resolved_database_url(self) -> str:
        """The database URL; default an SQLite file in ``data_dir``."""
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(self.data_dir / 'twindelta.db').resolve()}"

    @property
    def resolved_broker_url(self) -> str:
        """The broker URL; default Kombu's file-system transport (no server)."""
        return self.broker_url or "filesystem://"

    @property
    def is_embedded_broker(self) -> bool:
        return self.resolved_broker_url.startswith("filesystem://")

    @property
    def broker_dir(self) -> Path:
        """Folder of the file-system broker's messages (embedded mode only)."""
        return (self.data_dir / "broker").resolve()

    @property
    def resolved_console_dir(self) -> Path:
        return (
            self.console_dir or Path(__file__).resolve().parents[2] / "console" / "dist"
        ).resolve()

    @property
    def resolved_storage_dir(self) -> Path:
        return (self.storage_dir or self.data_dir / "files").resolve()

    @property
    def resolved_scratch_dir(self) -> Path:
        return (self.scratch_dir or self.data_dir / "scratch").resolve()


_BUCKET = re.compile(r"[a-z0-9][a-z0-9.-]{1,61}[a-z0-9]")


def parse_s3_url(url: str) -> tuple[str, str]:
    """``s3://bucket/optional/prefix`` as (bucket, prefix without slashes at either end);
    ValueError naming what is wrong."""
    scheme, sep, rest = url.partition("://")
    if scheme != "s3" or not sep:
        raise ValueError(f"TWINDELTA_STORAGE_URL: {url!r} is not s3://bucket[/prefix]")
    bucket, _, prefix = rest.partition("/")
    if not _BUCKET.fullmatch(bucket):
        raise ValueError(
            f"TWINDELTA_STORAGE_URL: {bucket!r} is not a bucket name (3-63 lowercase letters, "
            "digits, dots and hyphens)"
        )
    prefix = prefix.strip("/")
    if prefix and any(part in ("", ".", "..") for part in prefix.split("/")):
        raise ValueError(f"TWINDELTA_STORAGE_URL: the prefix {prefix!r} has an empty, . or .. part")
    return bucket, prefix


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    """The process-wide settings, read from the environment once."""
    return Settings()
