"""Which addresses may receive webhooks: a URL's host resolved once and every address checked
(public, or inside ``Settings.webhook_allowed_networks``)."""

from __future__ import annotations

import ipaddress
import socket
from collections.abc import Sequence
from dataclasses import dataclass
from urllib.parse import urlsplit

from app.core.errors import InvalidInput
from app.core.settings import Settings

IpAddress = ipaddress.IPv4Address | ipaddress.IPv6Address
Network = ipaddress.IPv4Network | ipaddress.IPv6Network


def allowed_networks(settings: Settings) -> list[Network]:
    """``Settings.webhook_allowed_networks`` parsed (CIDRs of private targets allowed)."""
    try:
        return [ipaddress.ip_network(n, strict=False) for n in settings.webhook_allowed_networks]
    except ValueError as exc:
        raise InvalidInput(f"TWINDELTA_WEBHOOK_ALLOWED_NETWORKS: {exc}") from exc


def _is_public(ip: IpAddress) -> bool:
    if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
        ip = ip.ipv4_mapped
    return ip.is_global and not ip.is_multicast


def _resolve(host: str, port: int) -> list[IpAddress]:
    try:
        return [ipaddress.ip_address(host)]
    except ValueError:
        pass
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except OSError as exc:
        raise InvalidInput(f"url: cannot resolve host {host!r} ({exc})") from exc
    return [ipaddress.ip_address(str(info[4][0]).split("%", 1)[0]) for info in infos]


@dataclass(frozen=True)
class Target:
    """A webhook URL's host resolved once, every address checked: the only addresses an
    attempt may connect to (a second lookup could answer differently: DNS rebinding)."""

    host: str
    port: int
    addresses: tuple[IpAddress, ...]


def resolve_target(url: str, networks: Sequence[Network]) -> Target:
    """Resolve ``url``'s host once and check every address it has; refuse (InvalidInput,
    422) a URL that is not http(s), or whose host is or resolves to a non-public address
    (loopback, RFC 1918, link-local, unique-local, ...) outside ``networks``."""
    try:
        parts = urlsplit(url)
        port = parts.port or (443 if parts.scheme == "https" else 80)
    except ValueError as exc:
        raise InvalidInput(f"url: {exc}") from exc
    if parts.scheme not in {"http", "https"}:
        raise InvalidInput("url: only http and https URLs can receive webhooks")
    if not parts.hostname:
        raise InvalidInput("url: the URL has no host")
    addresses = _resolve(parts.hostname, port)
    for ip in addresses:
        if _is_public(ip) or any(ip in net for net in networks):
            continue
        raise InvalidInput(
            f"url: {parts.hostname} is the non-public address {ip}; private targets need "
            "TWINDELTA_WEBHOOK_ALLOWED_NETWORKS",
            code="WebhookTargetRefused",
        )
    if not addresses:
        raise InvalidInput(f"url: host {parts.hostname!r} has no address")
    return Target(parts.hostname, port, tuple(dict.fromkeys(addresses)))


def check_target(url: str, networks: Sequence[Network]) -> None:
    """:func:`resolve_target` for its refusals only (when a subscription is made)."""
    resolve_target(url, networks)
