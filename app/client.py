"""A capture station's view of twindelta over HTTP (httpx): start the embedded service, upload
captures, poll jobs with progress. :class:`Client` is the typed client (environments by name,
resumable tus uploads with retries and resume, jobs with their stages, changes, the twin's
state) that the ``twindelta upload|changes|state`` commands use. Shared by the demo
(``workers.demo``), the benchmarks and the e2e tests. Imports nothing from the service
(import-linter checks it): the service is a child process, reached only over HTTP."""

from __future__ import annotations

import base64
import hashlib
import json
import os
import signal
import socket
import subprocess
import sys
import tarfile
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import httpx

REPO_ROOT = Path(__file__).resolve().parents[1]
FINAL = {"succeeded", "failed", "cancelled"}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


@contextmanager
def embedded_service(
    data_dir: Path, admin_key: str, log_path: Path, port: int | None = None, **settings: str
) -> Iterator[httpx.Client]:
    """``twindelta serve`` in a child process (SQLite, file-system broker); yields a client
    with the admin key; stops the service on exit."""
    port = port or free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("TWINDELTA_")}
    env.update(
        TWINDELTA_DATA_DIR=str(data_dir),
        TWINDELTA_BOOTSTRAP_ADMIN_KEY=admin_key,
        PYTHONUNBUFFERED="1",
    )
    env.update({f"TWINDELTA_{k.upper()}": v for k, v in settings.items()})
    log_path.parent.mkdir(parents=True, exist_ok=True)
    with log_path.open("ab") as log:
        proc = subprocess.Popen(
            [sys.executable, "-m", "app.cli", "serve", "--port", str(port)],
            cwd=REPO_ROOT,
            env=env,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
    client = httpx.Client(
        base_url=f"http://127.0.0.1:{port}",
        timeout=120,
        headers={"Authorization": f"Bearer {admin_key}"},
    )
    try:
        deadline = time.monotonic() + 90
        while True:
            if proc.poll() is not None:
                raise RuntimeError(f"the service exited with {proc.returncode}; see {log_path}")
            try:
                if client.get("/readyz").status_code == 200:
                    break
            except httpx.TransportError:
                pass
            if time.monotonic() > deadline:
                raise RuntimeError(f"the service did not start in 90 s; see {log_path}")
            time.sleep(0.3)
        yield client
    finally:
        client.close()
        if proc.poll() is None:
            # SIGTERM to serve alone: it stops its workers, which stop their pool children.
            # Sent to the whole group, it also reaches a CPU worker's pool child, and once
            # that child has loaded pycolmap its Celery parent hangs until serve's 20 s kill.
            proc.terminate()
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)


def check(response: httpx.Response, *expected: int) -> dict[str, Any]:
    if response.status_code not in expected:
        raise RuntimeError(
            f"{response.request.method} {response.request.url.path}: "
            f"{response.status_code} {response.text[:500]}"
        )
    body: dict[str, Any] = response.json()
    return body


def capture_parts(capture_dir: Path) -> list[tuple[str, Path]]:
    """The multipart fields of a capture folder (images/, labels/, cameras.json when there):
    (field name, file) pairs in upload order."""
    parts = [
        (field, path)
        for field, sub in (("images", "images"), ("detections", "labels"))
        for path in sorted((capture_dir / sub).iterdir())
    ]
    cameras = capture_dir / "cameras.json"
    return [*parts, ("cameras", cameras)] if cameras.exists() else parts


def upload_capture(
    client: httpx.Client, environment_id: str, capture_dir: Path, idempotency_key: str | None = None
) -> dict[str, Any]:
    """POST a capture folder (:func:`capture_parts`) as multipart files, streamed."""
    handles = []
    try:
        files: list[tuple[str, tuple[str, Any]]] = []
        for field, path in capture_parts(capture_dir):
            handle = path.open("rb")
            handles.append(handle)
            files.append((field, (path.name, handle)))
        headers = {"Idempotency-Key": idempotency_key} if idempotency_key else {}
        return check(
            client.post(
                f"/v1/environments/{environment_id}/snapshots", files=files, headers=headers
            ),
            202,
        )
    finally:
        for handle in handles:
            handle.close()


def poll_job(
    client: httpx.Client, job_id: str, label: str, timeout_s: float = 1800, quiet: bool = False
) -> dict[str, Any]:
    """Poll until the job is final, drawing a one-line progress bar; returns the job."""
    started = time.monotonic()
    last_line = ""
    while True:
        job = check(client.get(f"/v1/jobs/{job_id}"), 200)
        bar = "#" * int(job["progress"] * 30)
        line = f"  {label:<28} [{bar:<30}] {job['progress'] * 100:5.1f}%  {job['state']}"
        line += f" · {job['stage']}" if job.get("stage") else ""
        if not quiet and line != last_line:
            print("\r" + line.ljust(100), end="", flush=True)
            last_line = line
        if job["state"] in FINAL:
            if not quiet:
                print(f"  ({time.monotonic() - started:.0f} s)")
            return job
        if time.monotonic() - started > timeout_s:
            raise RuntimeError(f"{label}: job {job_id} not finished after {timeout_s} s")
        time.sleep(0.5)


def read_json(path: Path) -> Any:
    return json.loads(path.read_text())


# --- the typed client -----------------------------------------------------------------------

TUS_VERSION = "1.0.0"
DEFAULT_CHUNK_BYTES = 64 * 1024**2
READ_BYTES = 1024 * 1024
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")


class ApiError(RuntimeError):
    """An answer the client cannot go on from: ``status`` (0: no answer, the connection
    failed every retry), the service's ``code`` and ``detail``."""

    def __init__(self, status: int, code: str, detail: str, what: str) -> None:
        super().__init__(f"{what}: {status} {code}: {detail}")
        self.status, self.code, self.detail = status, code, detail

    @classmethod
    def of(cls, response: httpx.Response) -> ApiError:
        try:
            body = response.json()
            code, detail = str(body.get("error", "")), str(body.get("detail", ""))
        except (ValueError, AttributeError):
            code, detail = response.headers.get("Twindelta-Error", ""), response.text[:500]
        what = f"{response.request.method} {response.request.url.path}"
        return cls(response.status_code, code or "HTTPError", detail, what)


@dataclass(frozen=True)
class PackedCapture:
    """A capture folder packed into one tar: its ``path``, ``size`` (bytes), ``sha256``
    (hex) and what went in."""

    path: Path
    size: int
    sha256: str
    n_images: int
    n_labels: int
    has_cameras: bool

    @property
    def idempotency_key(self) -> str:
        """Derived from the content: the same capture packs to the same key."""
        return f"twindelta-cli:{self.sha256}"


def pack_capture(capture_dir: Path, out: Path) -> PackedCapture:
    """Pack the images (.jpg .jpeg .png), YOLO labels (.txt, classes.txt too) and
    cameras.json found anywhere in ``capture_dir`` into the tar ``out``, file by file (never
    whole in memory). Deterministic (sorted, no times or owners), so the same files give the
    same bytes and :attr:`PackedCapture.idempotency_key`. ValueError when there is no image."""
    files = sorted(
        p
        for p in capture_dir.rglob("*")
        if p.is_file()
        and not any(part.startswith(".") for part in p.relative_to(capture_dir).parts)
        and (p.suffix.lower() in (*IMAGE_SUFFIXES, ".txt") or p.name.lower() == "cameras.json")
    )
    n_images = sum(p.suffix.lower() in IMAGE_SUFFIXES for p in files)
    if n_images == 0:
        raise ValueError(f"{capture_dir}: no images (.jpg, .jpeg, .png) found")
    with tarfile.open(out, "w", format=tarfile.PAX_FORMAT) as tar:
        for path in files:
            info = tarfile.TarInfo(path.relative_to(capture_dir).as_posix())
            info.size, info.mode, info.mtime = path.stat().st_size, 0o644, 0
            with path.open("rb") as fh:
                tar.addfile(info, fh)
    digest = hashlib.sha256()
    with out.open("rb") as fh:
        while chunk := fh.read(4 * READ_BYTES):
            digest.update(chunk)
    return PackedCapture(
        path=out,
        size=out.stat().st_size,
        sha256=digest.hexdigest(),
        n_images=n_images,
        n_labels=sum(p.suffix.lower() == ".txt" for p in files),
        has_cameras=any(p.name.lower() == "cameras.json" for p in files),
    )


@dataclass(frozen=True)
class UploadResult:
    """A finished resumable upload: the snapshot and job it became, the bytes this client
    sent (resent ones included) and how often it resumed after a failure."""

    upload_url: str
    snapshot: str
    job: str
    bytes_sent: int
    resumes: int


def _metadata(values: dict[str, str]) -> str:
    return ",".join(f"{k} {base64.b64encode(v.encode()).decode()}" for k, v in values.items())


def _retryable(response: httpx.Response) -> bool:
    """Worth asking again after a wait: the service busy, restarting or locked (not a
    full disk, 507, which waiting does not fix)."""
    return response.status_code in (423, 429) or (
        response.status_code >= 500 and response.status_code not in (501, 507)
    )


def _resumable(response: httpx.Response) -> bool:
    """A PATCH answer after which the upload goes on from the offset HEAD gives."""
    if response.status_code == 409:
        try:
            return bool(response.json().get("error") == "OffsetMismatch")
        except ValueError:
            return False
    return _retryable(response)


class Client:
    """A typed client of one twindelta service over HTTP (thin, over httpx): environments by
    name or id, resumable uploads of captures, jobs with their stages, changes and the
    twin's state. Connection errors and 5xx/423/429 answers are retried ``retries`` times
    with exponential backoff (``backoff_s`` doubling up to ``max_backoff_s``); any other
    unexpected answer raises :class:`ApiError` with the service's code and detail."""

    def __init__(
        self,
        url: str,
        key: str | None,
        *,
        timeout_s: float = 60.0,
        retries: int = 8,
        backoff_s: float = 0.5,
        max_backoff_s: float = 30.0,
        transport: httpx.BaseTransport | None = None,
    ) -> None:
        headers = {"Authorization": f"Bearer {key}"} if key else {}
        self.http = httpx.Client(
            base_url=url.rstrip("/"), headers=headers, timeout=timeout_s, transport=transport
        )
        self.retries, self.backoff_s, self.max_backoff_s = retries, backoff_s, max_backoff_s
        self.sleep: Callable[[float], None] = time.sleep

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    def close(self) -> None:
        self.http.close()

    def _backoff(self, attempt: int) -> None:
        self.sleep(min(self.backoff_s * 2**attempt, self.max_backoff_s))

    def request(
        self, method: str, path: str, *, expected: tuple[int, ...] = (200,), **kwargs: Any
    ) -> httpx.Response:
        """One request with retries; the response when its status is ``expected``."""
        for attempt in range(self.retries + 1):
            try:
                response = self.http.request(method, path, **kwargs)
            except httpx.TransportError as exc:
                if attempt == self.retries:
                    raise ApiError(0, type(exc).__name__, str(exc), f"{method} {path}") from exc
                self._backoff(attempt)
                continue
            if response.status_code in expected:
                return response
            if not _retryable(response) or attempt == self.retries:
                raise ApiError.of(response)
            self._backoff(attempt)
        raise AssertionError("unreachable")

    def get(self, path: str, **params: Any) -> Any:
        """GET ``path`` → its JSON body."""
        return self.request("GET", path, params=params or None).json()

    # --- resources --------------------------------------------------------------------------

    def environments(self) -> list[dict[str, Any]]:
        """Every environment the key reaches."""
        found: list[dict[str, Any]] = self.get("/v1/environments")
        return found

    def environment(self, name_or_id: str) -> dict[str, Any]:
        """The environment with this id, else the one with this name; ApiError 404 when
        none (or more than one) matches."""
        matches = [e for e in self.environments() if name_or_id in (e["id"], e["name"])]
        by_id = [e for e in matches if e["id"] == name_or_id]
        if by_id or len(matches) == 1:
            return (by_id or matches)[0]
        detail = f"{len(matches)} environments are named {name_or_id!r}; give the id"
        if not matches:
            detail = f"no environment with the id or name {name_or_id!r}"
        raise ApiError(404, "NotFound", detail, "environment")

    def create_environment(self, name: str, classes: list[str], **fields: Any) -> dict[str, Any]:
        """POST /v1/environments (``reference``, ``options`` as keyword arguments)."""
        body = {"name": name, "classes": classes, **fields}
        created: dict[str, Any] = self.request(
            "POST", "/v1/environments", json=body, expected=(201,)
        ).json()
        return created

    def job(self, job_id: str) -> dict[str, Any]:
        found: dict[str, Any] = self.get(f"/v1/jobs/{job_id}")
        return found

    def snapshot(self, snapshot_id: str) -> dict[str, Any]:
        found: dict[str, Any] = self.get(f"/v1/snapshots/{snapshot_id}")
        return found

    def comparison(self, comparison_id: str) -> dict[str, Any]:
        found: dict[str, Any] = self.get(f"/v1/comparisons/{comparison_id}")
        return found

    def comparisons(self, environment_id: str) -> list[dict[str, Any]]:
        """The environment's comparisons, newest first."""
        found: list[dict[str, Any]] = self.get(f"/v1/environments/{environment_id}/comparisons")
        return found

    def import_objects(
        self, environment_id: str, body: bytes, content_type: str = "application/json"
    ) -> list[dict[str, Any]]:
        """Seed the twin with the platform's objects: ``body`` a JSON list or a CSV
        (``text/csv``), all or nothing; the instances made. Sent once, never retried (a
        retry after a lost answer could seed twice); ApiError (422) names the bad rows."""
        path = f"/v1/environments/{environment_id}/objects/import"
        try:
            response = self.http.post(path, content=body, headers={"Content-Type": content_type})
        except httpx.TransportError as exc:
            raise ApiError(0, type(exc).__name__, str(exc), f"POST {path}") from exc
        if response.status_code != 201:
            raise ApiError.of(response)
        made: list[dict[str, Any]] = response.json()
        return made

    def state(self, environment_id: str) -> dict[str, Any]:
        """The twin as it stands: ``objects`` (instances with poses) and ``twin``."""
        found: dict[str, Any] = self.get(f"/v1/environments/{environment_id}/state")
        return found

    def wait_job(
        self,
        job_id: str,
        on_job: Callable[[dict[str, Any]], None] | None = None,
        timeout_s: float = 3600.0,
        poll_s: float = 0.5,
    ) -> dict[str, Any]:
        """Poll until the job is final, calling ``on_job`` with each answer; returns it.
        TimeoutError after ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while True:
            job = self.job(job_id)
            if on_job is not None:
                on_job(job)
            if job["state"] in FINAL:
                return job
            if time.monotonic() > deadline:
                raise TimeoutError(f"job {job_id} not finished after {timeout_s} s")
            self.sleep(poll_s)

    def outcome(
        self, snapshot_id: str, timeout_s: float = 3600.0, poll_s: float = 0.5
    ) -> dict[str, Any] | None:
        """After a snapshot's job: its automatic comparison once that is final (None when the
        snapshot started the twin or was skipped). ApiError 409 ``TwinBlocked`` when an
        earlier failed comparison holds the twin; TimeoutError after ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while True:
            snap = self.snapshot(snapshot_id)
            if snap.get("comparison"):
                comparison = self.comparison(snap["comparison"])
                if self.job(comparison["job"])["state"] in FINAL:
                    return self.comparison(snap["comparison"])
            elif snap.get("twin_update") or snap["state"] in ("failed", "cancelled"):
                return None
            else:
                twin = self.get(f"/v1/environments/{snap['environment']}")["twin"]
                if twin["status"] == "blocked":
                    held = twin.get("comparison")
                    raise ApiError(
                        409,
                        "TwinBlocked",
                        f"comparison {held} failed and holds the twin before this snapshot; "
                        f"retry it (POST /v1/comparisons/{held}/retry)",
                        f"snapshot {snapshot_id}",
                    )
            if time.monotonic() > deadline:
                raise TimeoutError(f"snapshot {snapshot_id}: no outcome after {timeout_s} s")
            self.sleep(poll_s)

    # --- resumable uploads (tus 1.0) --------------------------------------------------------

    def upload(
        self,
        environment_id: str,
        archive: Path,
        *,
        sha256: str | None = None,
        idempotency_key: str | None = None,
        chunk_bytes: int = DEFAULT_CHUNK_BYTES,
        on_bytes: Callable[[int, int], None] | None = None,
    ) -> UploadResult:
        """Send the capture archive ``archive`` (.zip, .tar, .tar.gz) as a resumable
        upload in PATCHes of ``chunk_bytes``; after a dropped connection or a 5xx/409/423,
        wait (backoff), ask the offset (HEAD) and resume from it. ``sha256`` (hex; computed
        when not given) lets the service check the whole archive and, with
        ``idempotency_key``, find an earlier upload of it to resume or its snapshot.
        ``on_bytes(offset, size)`` reports progress. ApiError when the service refuses the
        archive or the connection keeps failing."""
        size = archive.stat().st_size
        sha256 = sha256 or _file_sha256(archive)
        meta = {"environment_id": environment_id, "filename": archive.name, "sha256": sha256}
        if idempotency_key:
            meta["idempotency_key"] = idempotency_key
        created = self.request(
            "POST",
            "/v1/uploads",
            expected=(201,),
            headers={
                "Tus-Resumable": TUS_VERSION,
                "Upload-Length": str(size),
                "Upload-Metadata": _metadata(meta),
            },
        )
        url = created.headers["Location"]
        offset = int(created.headers.get("Upload-Offset", "0"))
        sent = resumes = failures = 0
        answer: httpx.Response = created
        with archive.open("rb") as fh:
            while "Twindelta-Snapshot" not in answer.headers:
                if on_bytes is not None:
                    on_bytes(offset, size)
                n = min(chunk_bytes, size - offset)
                try:
                    answer = self._patch(url, fh, offset, n, size, on_bytes)
                    sent += n
                except httpx.TransportError as exc:
                    sent += n  # at most; the HEAD says what arrived
                    answer = self._failed(url, exc, failures)
                if answer.status_code == 204:
                    offset, failures = int(answer.headers["Upload-Offset"]), 0
                    continue
                if answer.status_code != 200 and not _resumable(answer):
                    raise ApiError.of(answer)
                failures, resumes = failures + 1, resumes + 1
                if failures > self.retries:
                    raise ApiError.of(answer)
                self._backoff(failures - 1)
                offset = self._offset(url)
                answer = httpx.Response(200, request=answer.request)
        if on_bytes is not None:
            on_bytes(size, size)
        return UploadResult(
            upload_url=url,
            snapshot=answer.headers["Twindelta-Snapshot"],
            job=answer.headers["Twindelta-Job"],
            bytes_sent=sent,
            resumes=resumes,
        )

    def _patch(
        self,
        url: str,
        fh: BinaryIO,
        offset: int,
        n: int,
        size: int,
        on_bytes: Callable[[int, int], None] | None,
    ) -> httpx.Response:
        """One PATCH of ``n`` bytes of ``fh`` from ``offset``, streamed from the file."""

        def body() -> Iterator[bytes]:
            fh.seek(offset)
            left, at = n, offset
            while left > 0:
                chunk = fh.read(min(READ_BYTES, left))
                if not chunk:
                    raise OSError(f"{fh.name}: shorter than {size} bytes (changed while sent?)")
                left, at = left - len(chunk), at + len(chunk)
                yield chunk
                if on_bytes is not None:
                    on_bytes(at, size)

        return self.http.patch(
            url,
            content=body(),
            headers={
                "Tus-Resumable": TUS_VERSION,
                "Content-Type": "application/offset+octet-stream",
                "Content-Length": str(n),
                "Upload-Offset": str(offset),
            },
        )

    def _failed(self, url: str, exc: httpx.TransportError, failures: int) -> httpx.Response:
        """A PATCH whose connection failed: a stand-in answer that makes the loop resume
        (ApiError once the retries are spent)."""
        if failures >= self.retries:
            raise ApiError(0, type(exc).__name__, str(exc), f"PATCH {url}") from exc
        return httpx.Response(503, request=httpx.Request("PATCH", url))

    def _offset(self, url: str) -> int:
        """The upload's offset (HEAD, with retries)."""
        response = self.request("HEAD", url, headers={"Tus-Resumable": TUS_VERSION})
        return int(response.headers["Upload-Offset"])

    def upload_capture(
        self,
        environment_id: str,
        capture_dir: Path,
        *,
        workdir: Path | None = None,
        chunk_bytes: int = DEFAULT_CHUNK_BYTES,
        on_bytes: Callable[[int, int], None] | None = None,
    ) -> UploadResult:
        """Pack ``capture_dir`` (:func:`pack_capture`, in a temporary folder under
        ``workdir``) and upload it resumably with its content-derived Idempotency-Key, so a
        re-run never makes a second snapshot."""
        with tempfile.TemporaryDirectory(prefix="twindelta-upload-", dir=workdir) as tmp:
            packed = pack_capture(capture_dir, Path(tmp) / "capture.tar")
            return self.upload(
                environment_id,
                packed.path,
                sha256=packed.sha256,
                idempotency_key=packed.idempotency_key,
                chunk_bytes=chunk_bytes,
                on_bytes=on_bytes,
            )


def _file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as fh:
        while chunk := fh.read(4 * READ_BYTES):
            digest.update(chunk)
    return digest.hexdigest()
