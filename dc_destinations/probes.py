"""Helpers for the destinations' read-only probes (``Destination.probe``, run by ``dc check``)."""

from __future__ import annotations

import socket
import ssl

from dc_core.destination import ProbeResult
from dc_destinations.tls import ssl_reason


def connect_probe(
    host: str, port: int, timeout: float, tls: ssl.SSLContext | None, *, server_name: str = "", what: str = ""
) -> ProbeResult:
    """Open a TCP connection to ``host:port`` (with the TLS handshake when ``tls``), send nothing, close it."""
    where = what or f"{host}:{port}"
    try:
        sock = socket.create_connection((host, port), timeout=timeout)
    except TimeoutError:
        return ProbeResult(False, f"cannot connect to {where}: no answer within {timeout:g} s", "check host and port")
    except OSError as exc:
        return ProbeResult(False, f"cannot connect to {where}: {ssl_reason(exc)}", "check host and port")
    try:
        if tls is not None:
            try:
                tls.wrap_socket(sock, server_hostname=server_name or host).close()
            except (OSError, ssl.SSLError) as exc:
                return ProbeResult(
                    False,
                    f"TLS handshake with {where} failed: {ssl_reason(exc)}",
                    "check the CA file (tls_ca_file / sslrootcert) and the host name the certificate names",
                )
            return ProbeResult(True, f"connected to {where}, TLS certificate accepted")
    finally:
        sock.close()
    return ProbeResult(True, f"connected to {where}")
