"""Transport security decisions every destination shares: is a host on this machine, and do credentials travel in clear.

One place on purpose: each destination used to decide TLS its own way. A destination's
``on_configure`` calls :func:`warn_if_credentials_in_clear` once with what it sends and how it
connects; the rule, the wording and the fix live here. Nothing here connects or resolves a name
(configure does no I/O): a host name other than ``localhost`` counts as remote.
"""

from __future__ import annotations

import ipaddress
from urllib.parse import urlsplit

from dc_core.logs import Logger

# Names that resolve to loopback by definition (RFC 6761 reserves .localhost), without asking DNS.
_LOOPBACK_NAMES = ("localhost", "localhost.localdomain", "ip6-localhost", "ip6-loopback")


def is_loopback(host: str) -> bool:
    """Whether ``host`` (a name, an IPv4/IPv6 literal, IPv6 maybe in brackets) is this machine's loopback.

    A name is judged by its spelling only: ``robot.local`` counts as remote even if it resolves to
    127.0.1.1, so the warning errs on the side of being said.
    """
    name = host.strip().strip("[]").rstrip(".").lower()
    if not name:
        return False
    if name in _LOOPBACK_NAMES or name.endswith(".localhost"):
        return True
    try:
        address = ipaddress.ip_address(name.split("%", 1)[0])  # a zone index (fe80::1%eth0) is not part of it
    except ValueError:
        return False
    if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
        return address.ipv4_mapped.is_loopback
    return address.is_loopback


def url_host(url: str) -> str:
    """The host of ``url`` (empty when it has none), for the destinations configured with a URL."""
    try:
        return urlsplit(url).hostname or ""
    except ValueError:
        return ""


def url_is_verified_tls(url: str) -> bool:
    """Whether ``url`` is https (the clients DC uses check the certificate and host name of https by default)."""
    return url.lower().startswith("https://")


# Header or query parameter names that carry a credential by convention.
_CREDENTIAL_NAMES = ("authorization", "proxy-authorization", "cookie")
_CREDENTIAL_PARTS = ("token", "api-key", "apikey", "api_key", "secret", "password", "passwd", "signature")


def is_credential_name(name: str) -> bool:
    """Whether a header or query parameter of this name conventionally carries a credential."""
    lowered = name.strip().lower()
    return lowered in _CREDENTIAL_NAMES or any(part in lowered for part in _CREDENTIAL_PARTS)


def credentials_in_clear(host: str, *, credentials: str, verified_tls: bool) -> bool:
    """Whether credentials (non-empty ``credentials`` names them) would reach a remote host without verified TLS."""
    return bool(credentials) and not verified_tls and not is_loopback(host)


def warn_if_credentials_in_clear(
    logger: Logger,
    destination: str,
    host: str,
    *,
    credentials: str,
    verified_tls: bool,
    fix: str,
) -> bool:
    """Log one WARN when ``credentials`` go to a remote ``host`` without verified TLS; True if it did.

    ``credentials`` says what is sent ("password of user dc", "bearer token"), empty when nothing
    is; ``verified_tls`` whether the connection checks the server's certificate and host name;
    ``fix`` the setting that would make it so, in the destination's own keys. A warning, not an
    error: a closed network (a robot's own VLAN, a VPN) may be a deliberate choice, and a robot
    must keep collecting. Called from ``on_configure``, so said once per configuration, not per batch.
    """
    if not credentials_in_clear(host, credentials=credentials, verified_tls=verified_tls):
        return False
    logger.warning(
        f"destination {destination}: {credentials} sent to {host} without verified TLS: anyone on the "
        f"network path can read it (and the records); {fix}"
    )
    return True
