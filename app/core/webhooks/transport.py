"""One attempt's connection: resolved once within the attempt's deadline, pinned to the checked
addresses (no second lookup a rebinding DNS server could answer differently, no proxy), every
socket operation bounded by the deadline, TLS verified against the URL's host name."""

from __future__ import annotations

import contextlib
import socket
import ssl
import threading
import time
from collections.abc import Iterable, Sequence
from functools import lru_cache
from typing import Any

import httpcore
import httpx

from app.core.errors import InvalidInput
from app.core.webhooks.targets import IpAddress, Network, Target, resolve_target


@lru_cache(maxsize=1)
def tls_context() -> ssl.SSLContext:
    """The verifying TLS context, built once per process (it costs ~50 ms): certifi's CAs,
    or the operator's from ``SSL_CERT_FILE`` / ``SSL_CERT_DIR`` (receivers behind a private
    CA). Certificates are verified against the URL's host name."""
    return httpx.create_ssl_context()


class Deadline:
    """The monotonic instant by which one attempt ends, whatever the receiver does."""

    def __init__(self, at: float) -> None:
        self.at = at

    def left(self) -> float:
        return self.at - time.monotonic()

    def clip(self, timeout: float | None, error: type[Exception]) -> float:
        """``timeout`` cut to what is left; ``error`` once nothing is."""
        left = self.left()
        if left <= 0:
            raise error("the attempt's deadline passed")
        return left if timeout is None else min(timeout, left)


class _PinnedStream(httpcore.NetworkStream):
    """A connection whose every read, write and TLS handshake ends by the deadline."""

    def __init__(self, inner: httpcore.NetworkStream, backend: PinnedBackend) -> None:
        self._inner, self._backend, self._deadline = inner, backend, backend.deadline

    def read(self, max_bytes: int, timeout: float | None = None) -> bytes:
        return self._inner.read(max_bytes, self._deadline.clip(timeout, httpcore.ReadTimeout))

    def write(self, buffer: bytes, timeout: float | None = None) -> None:
        self._inner.write(buffer, self._deadline.clip(timeout, httpcore.WriteTimeout))

    def close(self) -> None:
        self._inner.close()

    def start_tls(
        self,
        ssl_context: ssl.SSLContext,
        server_hostname: str | None = None,
        timeout: float | None = None,
    ) -> httpcore.NetworkStream:
        clipped = self._deadline.clip(timeout, httpcore.ConnectTimeout)
        tls = self._inner.start_tls(ssl_context, server_hostname, clipped)
        return self._backend.track(tls)

    def get_extra_info(self, info: str) -> Any:
        return self._inner.get_extra_info(info)


class PinnedBackend(httpcore.NetworkBackend):
    """Connects only to the addresses that passed the check: the host name is never looked
    up again, so a DNS answer that changes after the check cannot send the attempt
    elsewhere. TLS still gets the URL's host name (httpcore passes it to ``start_tls``), so
    SNI and certificate verification are those of the name, and the Host header is the
    URL's. Every socket operation ends by the attempt's deadline, and :meth:`abort` shuts
    the sockets down (the watchdog's backstop for a TLS handshake that trickles in)."""

    def __init__(self, addresses: Sequence[IpAddress], deadline: Deadline) -> None:
        self._addresses, self.deadline = list(addresses), deadline
        self._inner = httpcore.SyncBackend()
        self._streams: list[httpcore.NetworkStream] = []
        self._lock = threading.Lock()

    def connect_tcp(
        self,
        host: str,
        port: int,
        timeout: float | None = None,
        local_address: str | None = None,
        socket_options: Iterable[Any] | None = None,
    ) -> httpcore.NetworkStream:
        error: Exception = httpcore.ConnectError(f"{host} has no checked address")
        for ip in self._addresses:
            try:
                stream = self._inner.connect_tcp(
                    str(ip),
                    port,
                    timeout=self.deadline.clip(timeout, httpcore.ConnectTimeout),
                    local_address=local_address,
                    socket_options=socket_options,
                )
            except httpcore.ConnectError as exc:  # try the next address
                error = exc
                continue
            return self.track(stream)
        raise error

    def track(self, stream: httpcore.NetworkStream) -> _PinnedStream:
        """Wrap a new stream (TCP, or TLS over it: a new socket object) for :meth:`abort`."""
        with self._lock:
            self._streams.append(stream)
        return _PinnedStream(stream, self)

    def connect_unix_socket(
        self,
        path: str,
        timeout: float | None = None,
        socket_options: Iterable[Any] | None = None,
    ) -> httpcore.NetworkStream:
        raise httpcore.ConnectError("webhooks are not sent to unix sockets")

    def sleep(self, seconds: float) -> None:
        time.sleep(seconds)

    def abort(self) -> None:
        with self._lock:
            streams = list(self._streams)
        for stream in streams:
            with contextlib.suppress(AttributeError, OSError):  # closed, or detached by TLS
                stream.get_extra_info("socket").shutdown(socket.SHUT_RDWR)


class Refused(Exception):
    pass


def resolve_within(url: str, networks: Sequence[Network], deadline: Deadline) -> Target:
    """:func:`resolve_target` within the deadline (``getaddrinfo`` has no timeout of its
    own: it runs in a helper thread that is left to finish on its own if it is late)."""
    result: list[Target | InvalidInput] = []
    done = threading.Event()

    def run() -> None:
        try:
            result.append(resolve_target(url, networks))
        except InvalidInput as exc:
            result.append(exc)
        finally:
            done.set()

    threading.Thread(target=run, name="webhook-resolve", daemon=True).start()
    if not done.wait(max(deadline.left(), 0.0)):
        raise httpcore.ConnectTimeout("resolving the host took past the deadline")
    if isinstance(result[0], InvalidInput):
        raise Refused(result[0].detail)
    return result[0]
