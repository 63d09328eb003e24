"""A private PKI for the TLS tests, made with the `cryptography` package: CA, server and client certificates.

One for every destination's TLS tests (HTTP, MQTT, TCP, InfluxDB) so that they test the same
certificates: the server's names ``localhost`` and ``127.0.0.1``, the client's key encrypted with
:data:`KEY_PASSWORD`, and a stranger CA that signed none of them (a wrong ``tls_ca_file``).
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import ssl
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID

KEY_PASSWORD = "client-key-pa55-Very-Secret"
CLIENT_NAME = "robot-c3po"


@dataclass(frozen=True)
class Pki:
    ca: Path
    server_crt: Path
    server_key: Path
    client_crt: Path  # common name CLIENT_NAME
    client_key: Path  # encrypted with KEY_PASSWORD
    stranger_ca: Path  # a CA that signed none of these

    def client_params(self) -> dict[str, Any]:
        """A destination's flat TLS parameters: this CA trusted, the client certificate and its encrypted key."""
        return {
            "tls": True,
            "tls_ca_file": str(self.ca),
            "tls_crt_file": str(self.client_crt),
            "tls_key_file": str(self.client_key),
            "tls_key_passwd": KEY_PASSWORD,
        }

    def server_context(self, *, client_ca: Path | None = None) -> ssl.SSLContext:
        """A server's context with this PKI's certificate; ``client_ca``: mutual TLS, a client certificate of it required."""
        context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
        context.load_cert_chain(str(self.server_crt), str(self.server_key))
        if client_ca is not None:
            context.verify_mode = ssl.CERT_REQUIRED
            context.load_verify_locations(str(client_ca))
        return context


def make_pki(folder: Path, name: str = "fleet") -> Pki:
    """A CA named ``name``, its server and client certificates, and a stranger CA, as PEM files in ``folder``."""
    ca_name, ca_key = _issue(folder, f"{name}-ca", f"{name} test CA", None)
    _, server_key = _issue(folder, f"{name}-server", "localhost", (ca_name, ca_key), server=True)
    _, client_key = _issue(folder, f"{name}-client", CLIENT_NAME, (ca_name, ca_key))
    _issue(folder, f"{name}-stranger", f"{name} stranger CA", None)
    return Pki(
        ca=folder / f"{name}-ca.crt",
        server_crt=folder / f"{name}-server.crt",
        server_key=_write_key(folder / f"{name}-server.key", server_key),
        client_crt=folder / f"{name}-client.crt",
        client_key=_write_key(folder / f"{name}-client.key", client_key, KEY_PASSWORD),
        stranger_ca=folder / f"{name}-stranger.crt",
    )


def _issue(
    folder: Path,
    stem: str,
    common_name: str,
    issuer: tuple[x509.Name, ec.EllipticCurvePrivateKey] | None,
    *,
    server: bool = False,
) -> tuple[x509.Name, ec.EllipticCurvePrivateKey]:
    key = ec.generate_private_key(ec.SECP256R1())
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)])
    issuer_name, issuer_key = issuer if issuer is not None else (subject, key)
    now = dt.datetime.now(dt.UTC)
    builder = (
        x509.CertificateBuilder()
        .subject_name(subject)
        .issuer_name(issuer_name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=1))
        .add_extension(x509.BasicConstraints(ca=issuer is None, path_length=None), critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
    )
    if issuer is not None:
        builder = builder.add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_public_key(issuer_key.public_key()), critical=False
        )
    else:  # OpenSSL 3 wants a CA's key usage to say it signs certificates
        builder = builder.add_extension(
            x509.KeyUsage(False, False, False, False, False, True, True, False, False), critical=True
        )
    if server:
        builder = builder.add_extension(
            x509.SubjectAlternativeName([x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]),
            critical=False,
        )
    certificate = builder.sign(issuer_key, hashes.SHA256())
    (folder / f"{stem}.crt").write_bytes(certificate.public_bytes(serialization.Encoding.PEM))
    return subject, key


def _write_key(path: Path, key: ec.EllipticCurvePrivateKey, password: str | None = None) -> Path:
    encryption: serialization.KeySerializationEncryption = (
        serialization.BestAvailableEncryption(password.encode()) if password else serialization.NoEncryption()
    )
    path.write_bytes(key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, encryption))
    return path
