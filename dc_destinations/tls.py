"""Transport security every destination shares: its TLS parameters and client context, is a host on
this machine, and do credentials travel in clear.

One place on purpose: each destination used to decide TLS its own way (three SSL contexts built in
three orders, three spellings of the parameters). A destination that connects mixes
:class:`TlsParams` into its parameters and builds its context with :func:`client_context` in
``on_configure``; it calls :func:`warn_if_credentials_in_clear` once with what it sends and how it
connects. The rule, the wording and the fix live here. Nothing here connects or resolves a name
(configure does no I/O): a host name other than ``localhost`` counts as remote.
"""

from __future__ import annotations

import dataclasses
import ipaddress
import os
import ssl
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlsplit

from dc_core.errors import ConfigError
from dc_core.logs import Logger
from dc_core.params import compat_param, param, parse_params

# The keys of the nested `tls:` section (TCP's original spelling) that mean a certificate was meant.
_FILE_KEYS = ("ca_file", "crt_file", "key_file", "key_passwd", "vhost")


@dataclass(frozen=True, kw_only=True)
class _NestedTls:
    """The original TCP output's `tls.*` keys, as a `tls:` section or dotted (`tls.active: on`)."""

    active: bool = param(False, doc="Use TLS")
    verify: bool = param(True, doc="Check the server's certificate and host name")
    debug: int = compat_param(1, "TLS failures are always logged with OpenSSL's reason", minimum=0, maximum=4)
    ca_file: str = param("", doc="CA certificates (PEM) to trust instead of the system's")
    crt_file: str = param("", doc="Client certificate (PEM), for servers that require one")
    key_file: str = param("", doc="Private key of crt_file (PEM), if not in crt_file")
    key_passwd: str = param("", secret=True, doc="Password of key_file (never logged)")
    vhost: str = param("", doc="Host name to check the certificate against and send as SNI; empty: host")

    def __post_init__(self) -> None:
        if self.key_file and not self.crt_file:
            raise ConfigError("key_file", "set crt_file too (the key belongs to a client certificate)")
        if self.key_passwd and not (self.key_file or self.crt_file):
            raise ConfigError("key_passwd", "set crt_file (and key_file) too")


@dataclass(frozen=True, kw_only=True, repr=False)
class TlsParams:
    """The TLS parameters of a destination that connects, mixed into its parameter class.

    The flat ``tls_*`` spelling (Fluent Bit's HTTP and MQTT outputs); a ``tls:`` section with
    ``active``, ``verify``, ``ca_file``… (its TCP output) is read as an alias of the same settings,
    and :func:`client_context` notes once that it is deprecated. After parsing ``tls`` is a boolean
    whatever the spelling, and an error names the key as the file spelled it (:meth:`tls_key`).
    """

    tls: bool | dict[str, Any] = param(
        False,
        section=_NestedTls,
        doc="Connect with TLS; the original TCP output's `tls:` section (active, verify, ...) is accepted too",
    )
    tls_verify: bool = param(True, doc="Check the server's certificate and host name (with `tls`)")
    tls_ca_file: str = param("", doc="CA certificates (PEM) to trust instead of the system's (with `tls`)")
    tls_crt_file: str = param("", doc="Client certificate (PEM) for servers that ask for one (with `tls`)")
    tls_key_file: str = param("", doc="Private key (PEM) of tls_crt_file, when not in the same file")
    tls_key_passwd: str = param("", secret=True, doc="Password of an encrypted tls_key_file (never logged)")

    def __post_init__(self) -> None:
        nested = isinstance(self.tls, dict)
        object.__setattr__(self, "_tls_nested", nested)  # not a parameter: how the file spelled them
        if isinstance(self.tls, dict):
            section = self.tls
            flat = [f.name for f in dataclasses.fields(TlsParams) if _set_flat(self, f)]
            if flat:
                raise ConfigError(flat[0], "write the TLS settings either as tls_* keys or as a tls: section, not both")
            settings = parse_params(_NestedTls, section, "tls")
            if "active" not in section and any(section.get(k) for k in _FILE_KEYS):
                # The original read a missing tls.active as off: certificates configured for a
                # connection that would go out in clear text are more likely a forgotten line.
                raise ConfigError("tls.active", "set tls.active: true (or false) beside the other tls.* keys")
            values = {
                "tls": settings.active,
                "tls_verify": settings.verify,
                "tls_ca_file": settings.ca_file,
                "tls_crt_file": settings.crt_file,
                "tls_key_file": settings.key_file,
                "tls_key_passwd": settings.key_passwd,
            }
            for name, value in values.items():
                object.__setattr__(self, name, value)
            if settings.vhost and hasattr(self, "tls_vhost"):
                object.__setattr__(self, "tls_vhost", settings.vhost)
            elif settings.vhost:
                raise ConfigError("tls.vhost", "this destination has no vhost setting")
        # (A section was checked by _NestedTls, in its own words.)
        if self.tls_key_file and not self.tls_crt_file:
            raise ConfigError("tls_key_file", "set tls_crt_file too (the key goes with a client certificate)")
        if self.tls_key_passwd and not (self.tls_key_file or self.tls_crt_file):
            raise ConfigError("tls_key_passwd", "set tls_key_file (or tls_crt_file) too")

    @property
    def tls_on(self) -> bool:
        """Whether TLS is on (``tls`` is a boolean after parsing; this says so to the type checker)."""
        return self.tls is True

    @property
    def tls_verified(self) -> bool:
        """Whether the connection checks the peer's certificate and host name."""
        return self.tls_on and self.tls_verify

    def tls_key(self, name: str) -> str:
        """The key of setting ``name`` (``ca_file``…) as the file spells it: ``tls_ca_file`` or ``tls.ca_file``."""
        return f"tls.{name}" if getattr(self, "_tls_nested", False) else f"tls_{name}"


def _set_flat(params: TlsParams, field: dataclasses.Field[Any]) -> bool:
    return field.name != "tls" and getattr(params, field.name) != field.default


def client_context(tls: TlsParams, path: str, logger: Logger | None = None) -> ssl.SSLContext | None:
    """The client SSL context of ``tls``; None when TLS is off.

    A CA, certificate or key file that does not load (missing, unreadable, not PEM, a key that does
    not match or a wrong ``tls_key_passwd``) is a :class:`ConfigError` naming its key under ``path``
    (``destination_server.<name>``): configure fails rather than every batch. The key password goes
    to OpenSSL only, and its messages never quote it. ``logger``: where the nested ``tls:`` section
    is noted as deprecated, once per configure.
    """
    if logger is not None and getattr(tls, "_tls_nested", False):
        logger.warning(
            f"{path}.tls: the tls: section (tls.active, tls.ca_file, ...) is deprecated; it still works, and "
            "the same settings are written tls: true, tls_ca_file, tls_crt_file, tls_key_file, tls_key_passwd, "
            "tls_verify"
        )
    if not tls.tls_on:
        return None
    files = (("ca_file", tls.tls_ca_file), ("crt_file", tls.tls_crt_file), ("key_file", tls.tls_key_file))
    for name, file in files:
        if file and not os.access(file, os.R_OK):
            problem = "no such file" if not os.path.exists(file) else "not readable"
            raise ConfigError(f"{path}.{tls.tls_key(name)}", f"cannot load {file}: {problem}")
    try:
        context = ssl.create_default_context(cafile=tls.tls_ca_file or None)
    except (OSError, ssl.SSLError) as exc:
        problem = f"cannot load {tls.tls_ca_file}: {ssl_reason(exc)}"
        raise ConfigError(f"{path}.{tls.tls_key('ca_file')}", problem) from None
    if tls.tls_crt_file:
        try:
            context.load_cert_chain(tls.tls_crt_file, tls.tls_key_file or None, password=tls.tls_key_passwd or None)
        except (OSError, ssl.SSLError) as exc:
            loaded = tls.tls_crt_file + (f" and {tls.tls_key_file}" if tls.tls_key_file else "")
            key = tls.tls_key("key_file" if tls.tls_key_file else "crt_file")
            raise ConfigError(
                f"{path}.{key}",
                f"cannot load {loaded}: {ssl_reason(exc)} (PEM certificate and key that match, "
                f"and the key's {tls.tls_key('key_passwd')} if it is encrypted)",
            ) from None
    if not tls.tls_verify:
        context.check_hostname = False
        context.verify_mode = ssl.CERT_NONE
    return context


def ssl_reason(exc: BaseException) -> str:
    """OpenSSL's reason for a TLS error ("certificate verify failed"); the errno text for another OSError."""
    if isinstance(exc, ssl.SSLError):
        return str(exc.reason or exc).lower().replace("_", " ")
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    return str(exc) or type(exc).__name__


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
