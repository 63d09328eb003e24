"""A receiver for tests of what reaches an HTTP server.

A real HTTP/1.1 server on 127.0.0.1, in threads of the test process.
"""

from __future__ import annotations

import contextlib
import json
import socket
import ssl
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from types import TracebackType
from typing import Any


@dataclass
class Request:
    time: float  # time.monotonic() at arrival
    path: str
    headers: list[tuple[str, str]]
    body: bytes
    client: tuple[str, int]
    status: int | None = None  # None: the connection was dropped without an answer

    def header(self, name: str) -> str | None:
        values = self.header_values(name)
        return values[-1] if values else None

    def header_values(self, name: str) -> list[str]:
        return [v for n, v in self.headers if n.lower() == name.lower()]


class _QuietServer(ThreadingHTTPServer):
    daemon_threads = True
    block_on_close = False

    def handle_error(self, request: Any, client_address: Any) -> None:
        """A client that hangs up while the answer is written (the huge-answer test) is expected."""


# What the receiver answers to a request: (status, body), or None to drop the connection unanswered.
Responder = Callable[[Request], "tuple[int, bytes] | None"]


class Receiver:
    """An HTTP endpoint whose answers the test sets (``status`` or ``respond``), keeping every request."""

    def __init__(
        self,
        respond: Responder | None = None,
        *,
        idle_timeout: float | None = None,
        tls: ssl.SSLContext | None = None,
        port: int = 0,
    ) -> None:
        self.status = 200
        self.respond = respond
        self.requests: list[Request] = []
        self.closed_connections = 0
        self.open_connections: set[socket.socket] = set()
        self.release = threading.Event()  # set at exit: lets a handler that hangs on purpose return
        self.changed = threading.Condition()
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"  # keep-alive, like a real endpoint
            timeout = idle_timeout  # closes a connection left idle this long

            def do_POST(self) -> None:
                length = int(self.headers.get("Content-Length", "0"))
                request = Request(
                    time.monotonic(),
                    self.path,
                    list(self.headers.items()),
                    self.rfile.read(length),
                    (str(self.client_address[0]), int(self.client_address[1])),
                )
                answer = receiver.answer(request)
                request.status = None if answer is None else answer[0]
                # Kept before answering: when the client has its answer, the test sees the request.
                with receiver.changed:
                    receiver.requests.append(request)
                    receiver.changed.notify_all()
                if answer is None:
                    self.close_connection = True
                    return
                self.send_response(answer[0])
                self.send_header("Content-Type", "text/plain")
                self.send_header("Content-Length", str(len(answer[1])))
                self.end_headers()
                self.wfile.write(answer[1])

            def setup(self) -> None:
                super().setup()
                with receiver.changed:
                    receiver.open_connections.add(self.connection)

            def finish(self) -> None:
                super().finish()
                with receiver.changed:
                    receiver.open_connections.discard(self.connection)
                    receiver.closed_connections += 1
                    receiver.changed.notify_all()

            def log_message(self, format: str, *args: Any) -> None:
                pass

        self.server = _QuietServer(("127.0.0.1", port), Handler)
        if tls is not None:
            self.server.socket = tls.wrap_socket(self.server.socket, server_side=True)
        self.port = int(self.server.server_address[1])
        self._thread = threading.Thread(target=self.server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)

    def answer(self, request: Request) -> tuple[int, bytes] | None:
        if self.respond is not None:
            return self.respond(request)
        return self.status, b"ok" if self.status < 300 else f"status {self.status} set by the test".encode()

    def __enter__(self) -> Receiver:
        self._thread.start()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.release.set()
        self.server.shutdown()
        self.server.server_close()
        # A stopped server closes its kept-alive connections too (server_close alone leaves them open).
        with self.changed:
            for connection in list(self.open_connections):
                with contextlib.suppress(OSError):
                    connection.shutdown(socket.SHUT_RDWR)

    def wait_until(self, check: Callable[[], bool], timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        with self.changed:
            while not check():
                left = deadline - time.monotonic()
                if left <= 0:
                    raise AssertionError(
                        f"timed out after {timeout} s waiting for {what}; {len(self.requests)} requests"
                    )
                self.changed.wait(min(left, 0.2))

    def accepted(self) -> list[Request]:
        with self.changed:
            return [r for r in self.requests if r.status is not None and 200 <= r.status < 300]

    def records(self) -> list[dict[str, Any]]:
        """Records of the accepted requests, in order (bodies of format json: JSON arrays)."""
        return [item for r in self.accepted() for item in json.loads(r.body)]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])
