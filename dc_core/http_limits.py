"""An HTTP server that a hostile or broken client cannot hold: bounded threads, socket timeouts, counted refusals.

The standard library's servers give either one request at a time (an idle connection blocks
everyone: a scraper's health check waits behind it forever) or one thread per connection without
bound (a flood of connections is a flood of threads). :class:`BoundedHTTPServer` serves each
connection in its own thread, at most ``max_connections`` at once; a connection beyond them gets
``503 Service Unavailable`` at once and is closed, and :attr:`BoundedHTTPServer.refused` counts it.
Every socket read and write has a timeout, so a connection that sends nothing frees its thread after
``timeout`` seconds.

The trade-off, said plainly: a client opening ``max_connections`` idle connections again and again
keeps the others waiting up to ``timeout`` at a time. The bound is on memory and threads, not on
service; these servers listen on loopback by default, where that client is already on the machine.
"""

from __future__ import annotations

import socket
import threading
from collections.abc import Callable
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

_BUSY = (
    b"HTTP/1.1 503 Service Unavailable\r\n"
    b"Content-Type: text/plain; charset=utf-8\r\n"
    b"Retry-After: 1\r\n"
    b"Connection: close\r\n"
    b"Content-Length: 25\r\n"
    b"\r\n"
    b"busy: too many requests\r\n"
)
# Refusing must not become the way to block the accepting thread: the 503 gets this long to go out.
_REFUSE_SEND_S = 0.2


class BoundedHTTPServer(ThreadingHTTPServer):
    """A ThreadingHTTPServer with at most ``max_connections`` handler threads and a socket ``timeout``.

    ``on_refused(total)`` is called on the accepting thread after each refusal (to log it); it must
    not block.
    """

    daemon_threads = True
    # Threads are not kept for a join at close: a handler stuck on a slow client must not hold a stop.
    block_on_close = False

    def __init__(
        self,
        address: tuple[str, int],
        handler: type[BaseHTTPRequestHandler],
        *,
        max_connections: int,
        timeout: float,
        on_refused: Callable[[int], None] | None = None,
    ) -> None:
        if max_connections < 1 or timeout <= 0:
            raise ValueError("max_connections >= 1 and timeout > 0")
        # The handler's own class attribute is what StreamRequestHandler applies to each connection.
        handler = type(handler.__name__, (handler,), {"timeout": timeout})
        self.max_connections = max_connections
        self.request_timeout = timeout
        self.refused = 0
        self._slots = threading.BoundedSemaphore(max_connections)
        self._on_refused = on_refused
        # An address family the host has (IPv6 for "::", "::1"): ThreadingHTTPServer assumes IPv4.
        if ":" in address[0]:
            self.address_family = socket.AF_INET6
        super().__init__(address, handler)

    def process_request(self, request: Any, client_address: Any) -> None:
        if not self._slots.acquire(blocking=False):
            self._refuse(request)
            return
        try:
            super().process_request(request, client_address)  # starts the handler's thread
        except BaseException:
            self._slots.release()
            raise

    def process_request_thread(self, request: Any, client_address: Any) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            self._slots.release()

    def _refuse(self, request: socket.socket) -> None:
        try:
            request.settimeout(_REFUSE_SEND_S)
            request.sendall(_BUSY)
        except OSError:
            pass  # the client went away or reads nothing: closed all the same
        self.shutdown_request(request)
        # Logged before it is counted: whoever sees the count can find the line.
        if self._on_refused is not None:
            self._on_refused(self.refused + 1)
        self.refused += 1
