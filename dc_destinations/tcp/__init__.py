"""TCP destination: records written to a TCP (or TLS) socket as JSON lines or msgpack, over a kept connection.

TCP gives no receipt: a record counts as sent once the kernel took it (the write returned). The
connection is opened with the first batch and kept; before each batch the socket is checked for a
peer that hung up (a read that finds the end of the stream), so a receiver that restarted is
reconnected to before anything is written into a dead connection. Records written in the instant
the peer dies can still be lost: the one case the durable buffer cannot cover (README.md).
"""

from __future__ import annotations

import socket
import ssl
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from dc_core.destination import Destination, OutgoingRecord, ProbeResult, RetryableError, SendOutcome
from dc_core.params import compat_param, host_param, param, port_problem, url_host
from dc_destinations.connection import Connection
from dc_destinations.msgpack_format import msgpack_packer
from dc_destinations.tls import TlsParams, client_context, ssl_reason

# "json" is the original's name for the same JSON lines.
FORMATS = ("json_lines", "json", "msgpack")
# Reads done before a batch to find out whether the peer hung up; what a receiver sends is discarded.
_PEEK_READS = 64


@dataclass(frozen=True, kw_only=True, repr=False)
class TcpParams(TlsParams):
    host: str = host_param("the TCP server")
    port: int = param(5432, check=port_problem, doc="TCP port of the server (the original's default: 5432)")
    format: str = param(
        "json_lines",
        choices=FORMATS,
        doc="json_lines (or json): one JSON object per line; msgpack: one msgpack map per record, back to back",
    )
    tls_vhost: str = param("", doc="Host name the certificate is checked against and sent as SNI; empty: host")
    connect_timeout: float = param(10.0, minimum=0.1, maximum=3600, doc="Seconds to connect (and the TLS handshake)")
    write_timeout: float = param(10.0, minimum=0.1, maximum=3600, doc="Seconds a write may block")
    workers: int = compat_param(2, "each destination has one sender, the destination server's", minimum=0)

    def __post_init__(self) -> None:
        super().__post_init__()

    def __repr__(self) -> str:
        # Written out to leave tls_key_passwd out.
        return (
            f"TcpParams(host={self.host!r}, port={self.port!r}, format={self.format!r}, tls={self.tls!r}, "
            f"tls_verify={self.tls_verify!r}, tls_ca_file={self.tls_ca_file!r}, tls_crt_file={self.tls_crt_file!r}, "
            f"tls_key_file={self.tls_key_file!r}, tls_vhost={self.tls_vhost!r}, "
            f"connect_timeout={self.connect_timeout!r}, write_timeout={self.write_timeout!r})"
        )

    __str__ = __repr__


class Tcp(Destination[TcpParams]):
    """Write records to a TCP or TLS server as JSON lines or msgpack, over a kept connection."""

    def __init__(self, context: Any, params: TcpParams) -> None:
        super().__init__(context, params)
        # The receiver may have hung up (restart, idle timeout) since the last batch: a new connection then.
        self._socket = self.keep(
            Connection("", self._connect, socket.socket.close, timeout=params.write_timeout, usable=self._peer_alive)
        )
        self._tls: ssl.SSLContext | None = None
        self._encode: Callable[[OutgoingRecord], bytes] = _json_line
        self._tls_failing = False
        self.address = ""

    # -- lifecycle -------------------------------------------------------------------------------
    def on_configure(self) -> None:
        p = self.params
        host = url_host(p.host)
        self.address = self._socket.where = f"{host}:{p.port}"
        self._socket.secrets = [p.tls_key_passwd]
        self._encode = _msgpack_encoder(self._key_path("format")) if p.format == "msgpack" else _json_line
        self._tls = client_context(p, self._key_path(""), self.context.logger)

    def on_activate(self) -> None:
        # The connection opens with the first batch, in the sender's thread: a server that is down
        # must not hold up activation.
        scheme = "TLS" if self._tls is not None else "TCP"
        self.context.logger.info(f"writing {self.params.format} records to {self.address} over {scheme}")

    def probe(self) -> ProbeResult:
        """A connection of its own, opened as the first batch opens one (TLS handshake included) and
        closed unused; the kept connection is left to ``send``."""
        self._connect().close()
        return ProbeResult(True, f"connected to {self.address}" + (" over TLS" if self._tls is not None else ""))

    # -- sending -----------------------------------------------------------------------------------
    def send(self, batch: Sequence[OutgoingRecord]) -> SendOutcome | None:
        frames = [self._encode(record) for record in batch]
        written, error = self._write(self._socket.get(), frames)
        if error is None:
            return None
        if written == 0:
            raise RetryableError(error)
        # The records wholly written before the failure went out; the rest wait in the buffer.
        return SendOutcome(retry=dict.fromkeys(range(written, len(frames)), error))

    def _write(self, sock: socket.socket, frames: list[bytes]) -> tuple[int, str | None]:
        """Write the frames: how many were wholly written, and why the write stopped (None: it did not)."""
        data = memoryview(b"".join(frames))
        ends, total = [], 0
        for frame in frames:
            total += len(frame)
            ends.append(total)
        sent = 0
        try:
            while sent < len(data):
                sent += sock.send(data[sent:])
        except OSError as exc:  # ssl.SSLError is an OSError too
            # A frame cut short leaves the stream mid-record: only a new connection is clean.
            self._socket.close()
            return sum(1 for end in ends if end <= sent), self._failure("cannot write to", exc)
        return len(frames), None

    def _peer_alive(self, sock: socket.socket) -> bool:
        """False when the peer closed or reset the connection; what it sent us is read and dropped."""
        sock.setblocking(False)
        try:
            for _ in range(_PEEK_READS):
                if not sock.recv(4096):
                    return False
        except (BlockingIOError, ssl.SSLWantReadError, ssl.SSLWantWriteError):
            return True
        except OSError:  # reset, or a TLS alert: the connection is unusable
            return False
        finally:
            sock.settimeout(self.params.write_timeout)
        return True  # a chatty peer: still there

    def _connect(self) -> socket.socket:
        p = self.params
        try:
            sock = socket.create_connection((p.host, p.port), timeout=p.connect_timeout)
        except OSError as exc:
            raise RetryableError(self._failure("cannot connect to", exc, p.connect_timeout)) from None
        try:
            if self._tls is not None:
                server_name = p.tls_vhost or p.host
                sock = self._tls.wrap_socket(sock, server_hostname=server_name)
        except ssl.SSLCertVerificationError as exc:
            sock.close()
            message = (
                f"TLS handshake with {self.address} failed: {exc.verify_message or exc.reason} "
                f"(check {self._key_path(p.tls_key('ca_file'))} and {p.tls_key('vhost')}, "
                f"or set {p.tls_key('verify')}: false on a test bench)"
            )
            if not self._tls_failing:  # a configuration problem: said once at ERROR, then by the sender's log
                self.context.logger.error(f"{message}; records wait in the buffer until it is fixed")
            self._tls_failing = True
            raise RetryableError(message) from None
        except (OSError, ssl.SSLError) as exc:
            sock.close()
            raise RetryableError(self._failure("TLS handshake failed with", exc, p.write_timeout)) from None
        self._tls_failing = False
        sock.settimeout(p.write_timeout)
        # Records go out as they are written rather than waiting to fill a segment.
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return sock

    # -- messages ----------------------------------------------------------------------------------
    def _key_path(self, key: str) -> str:
        return f"destination_server.{self.context.name}" + (f".{key}" if key else "")

    def _failure(self, what: str, exc: BaseException, timeout: float | None = None) -> str:
        return self._socket.failure(what, exc, detail=ssl_reason(exc), timeout=timeout, waiting="no progress")


def _json_line(record: OutgoingRecord) -> bytes:
    return (record.to_json() + "\n").encode("utf-8")


def _msgpack_encoder(path: str) -> Callable[[OutgoingRecord], bytes]:
    pack = msgpack_packer(path)
    return lambda record: pack(record.data)
