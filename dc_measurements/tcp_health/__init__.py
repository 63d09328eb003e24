"""TCPHealth measurement: whether a TCP server accepts connections."""

from __future__ import annotations

import ipaddress
import socket
import time
from collections.abc import Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import dataclass
from typing import Any

from dc_core.measurement import Measurement, MeasurementContext
from dc_core.params import param

_AddrInfo = Sequence[tuple[socket.AddressFamily, socket.SocketKind, int, str, tuple[Any, ...]]]


@dataclass(frozen=True, kw_only=True)
class TcpHealthParams:
    name: str = param(doc="Alias of the TCP server, reported as server_name")
    host: str = param("127.0.0.1", doc="Host name or IP address of the server")
    port: int = param(80, minimum=1, maximum=65535, doc="TCP port of the server")
    timeout: int = param(500, minimum=1, maximum=10000, doc="Milliseconds allowed to resolve and connect")


class TcpHealth(Measurement[TcpHealthParams]):
    """Whether a TCP server accepts connections on host:port (a real connect with a timeout)."""

    def __init__(self, context: MeasurementContext, params: TcpHealthParams) -> None:
        super().__init__(context, params)
        self._resolver: ThreadPoolExecutor | None = None
        self._pending: Future[_AddrInfo] | None = None

    def on_configure(self) -> None:
        if not _is_ip_literal(self.params.host):
            # getaddrinfo cannot be cancelled; running it in a worker keeps collect within `timeout`.
            self._resolver = ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"{self.context.name}-dns")

    def on_cleanup(self) -> None:
        if self._resolver is not None:
            self._resolver.shutdown(wait=False, cancel_futures=True)
            self._resolver = None

    def collect(self) -> dict[str, Any]:
        p = self.params
        return {"host": p.host, "port": p.port, "server_name": p.name, "active": self._connects()}

    def _connects(self) -> bool:
        deadline = time.monotonic() + self.params.timeout / 1000.0
        addresses = self._resolve(deadline)
        for family, kind, proto, _, address in addresses:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
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

    def _resolve(self, deadline: float) -> _AddrInfo:
        host, port = self.params.host, self.params.port
        if self._resolver is None:
            return _getaddrinfo(host, port)
        if self._pending is None or self._pending.done():
            self._pending = self._resolver.submit(_getaddrinfo, host, port)
        # A resolution still hanging from an earlier collect is awaited, not queued again.
        try:
            return self._pending.result(timeout=max(0.0, deadline - time.monotonic()))
        except FutureTimeout:
            self.context.logger.debug(f"{self.context.name}: resolving {host} timed out")
            return []
        except OSError as exc:
            self.context.logger.debug(f"{self.context.name}: cannot resolve {host}: {exc}")
            return []


def _is_ip_literal(host: str) -> bool:
    try:
        ipaddress.ip_address(host)
    except ValueError:
        return False
    return True


def _getaddrinfo(host: str, port: int) -> _AddrInfo:
    return socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
