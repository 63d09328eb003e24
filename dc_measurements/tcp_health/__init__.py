"""TCPHealth measurement: whether a TCP server accepts connections."""

from __future__ import annotations

import socket
import time
from dataclasses import dataclass
from typing import Any

from dc_core.measurement import Measurement
from dc_core.params import param


@dataclass(frozen=True, kw_only=True)
class TcpHealthParams:
    name: str = param(doc="Alias of the TCP server, reported as server_name")
    host: str = param("127.0.0.1", doc="Host name or IP address of the server")
    port: int = param(80, minimum=1, maximum=65535, doc="TCP port of the server")
    timeout: int = param(500, minimum=1, maximum=10000, doc="Milliseconds allowed to resolve and connect")


class TcpHealth(Measurement[TcpHealthParams]):
    """Whether a TCP server accepts connections on host:port (a real connect with a timeout)."""

    # Resolving and connecting wait (up to `timeout`, or longer for a resolver that hangs): on the
    # server's worker, the wait holds up no other measurement, record or heartbeat.
    collect_in_worker = True

    def collect(self) -> dict[str, Any]:
        p = self.params
        return {"host": p.host, "port": p.port, "server_name": p.name, "active": self._connects()}

    def _connects(self) -> bool:
        deadline = time.monotonic() + self.params.timeout / 1000.0
        host, port = self.params.host, self.params.port
        try:
            # getaddrinfo takes no timeout (an IP address returns at once): one that answers after the
            # deadline counts as not connecting.
            addresses = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
        except OSError as exc:
            self.context.logger.debug(f"{self.context.name}: cannot resolve {host}: {exc}")
            return False
        for family, kind, proto, _, address in addresses:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                self.context.logger.debug(f"{self.context.name}: {host}:{port} not reached within the timeout")
                return False
            with socket.socket(family, kind, proto) as sock:
                sock.settimeout(remaining)
                try:
                    sock.connect(address)
                except OSError as exc:
                    self.context.logger.debug(f"{self.context.name}: connect to {address} failed: {exc}")
                    continue
                return True
        return False
