"""Health and metrics of a DC server over HTTP, the paths Fluent Bit users know (``/api/v1/...``).

Standard library only. Each connection is served by its own daemon thread, at most
:data:`MAX_CONNECTIONS` at once, each socket with a timeout (dc_core.http_limits): a client that
connects and sends nothing no longer blocks ``/api/v1/health`` for the supervisor and the scraper.
Connections beyond the cap get a 503 and are counted (``metrics_http.refused_connections`` in the
JSON, ``dc_http_refused_connections_total``). Bound to loopback unless ``http_listen`` says
otherwise. Each server brings its own documents; :class:`PrometheusText` writes its counters in the
text format.
"""

from __future__ import annotations

import errno
import json
import logging
import time
from collections.abc import Callable, Mapping, Sequence
from http.server import BaseHTTPRequestHandler
from pathlib import Path
from typing import Any

from dc_core.http_limits import BoundedHTTPServer
from dc_core.logs import Logger
from dc_core.metrics_registry import announce, withdraw
from dc_core.supervision import Supervisor

# Where a StatusServer made without a supervisor (tests) says its thread died.
_STDERR_LOGGER = logging.getLogger("dc.status_http")

# A scraper, `dc status`, the supervisor's probe and an operator's curl at once, with room to spare;
# each thread costs little, and the cap is what keeps a flood of connections from costing more.
MAX_CONNECTIONS = 8
# Seconds a connection may stay silent while its request is read or its answer written.
REQUEST_TIMEOUT_S = 5.0
REFUSALS_LOG_INTERVAL_S = 60.0


class _Handler(BaseHTTPRequestHandler):
    server: _Server

    def do_GET(self) -> None:
        path = self.path.split("?", 1)[0].rstrip("/")
        try:
            if path == "/api/v1/health":
                health = self.server.health()
                # A bool, or a document whose status says more (a destination server's "degraded").
                document = health if isinstance(health, dict) else {"status": "ok" if health else "error"}
                ok = document.get("status") == "ok"
                self._reply(200 if ok else 503, "application/json", json.dumps(document))
            elif path == "/api/v1/metrics":
                document = {**self.server.metrics(), "metrics_http": {"refused_connections": self.server.refused}}
                self._reply(200, "application/json", json.dumps(document, indent=2))
            elif path == "/api/v1/metrics/prometheus":
                text = PrometheusText()
                text.family(
                    "dc_http_refused_connections_total",
                    "counter",
                    "Connections to this metrics server refused: as many as it serves at once were open",
                    [("", self.server.refused)],
                )
                body = self.server.prometheus() + text.text()
                self._reply(200, "text/plain; version=0.0.4; charset=utf-8", body)
            else:
                self._reply(404, "application/json", json.dumps({"error": f"no such path: {path}"}))
        except Exception as exc:  # a broken metric must not take the server down
            self._reply(500, "application/json", json.dumps({"error": str(exc)}))

    def _reply(self, status: int, content_type: str, body: str) -> None:
        data = body.encode("utf-8")
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(data)))
        self.end_headers()
        self.wfile.write(data)

    def log_message(self, format: str, *args: Any) -> None:
        """Requests are not logged: a scraper every few seconds would flood the log."""


class _Server(BoundedHTTPServer):
    def __init__(
        self,
        address: tuple[str, int],
        health: Callable[[], bool | dict[str, Any]],
        metrics: Callable[[], dict[str, Any]],
        prometheus: Callable[[], str],
        logger: Logger | None,
        max_connections: int,
        timeout: float,
    ) -> None:
        self.health = health
        self.metrics = metrics
        self.prometheus = prometheus
        self._logger = logger
        self._max_connections = max_connections
        self._refusals_logged_at: float | None = None
        super().__init__(address, _Handler, max_connections=max_connections, timeout=timeout, on_refused=self._refused)

    def _refused(self, total: int) -> None:
        # A line of its own rather than a BurstLog: rclpy fixes one severity per call site and logger,
        # and the server's logger already logs errors through BurstLog's.
        now = time.monotonic()
        if self._logger is None or (
            self._refusals_logged_at is not None and now - self._refusals_logged_at < REFUSALS_LOG_INTERVAL_S
        ):
            return
        self._refusals_logged_at = now
        self._logger.warning(
            f"metrics HTTP server: connection refused, {self._max_connections} being served "
            f"({total} refused since start; said at most once a minute, counted in metrics_http)"
        )


class StatusServer:
    """Serves ``/api/v1/health``, ``/api/v1/metrics`` and ``/api/v1/metrics/prometheus``."""

    def __init__(
        self,
        listen: str,
        port: int,
        *,
        health: Callable[[], bool | dict[str, Any]],
        metrics: Callable[[], dict[str, Any]],
        prometheus: Callable[[], str],
        logger: Logger | None = None,
        max_connections: int = MAX_CONNECTIONS,
        timeout: float = REQUEST_TIMEOUT_S,
        supervisor: Supervisor | None = None,
    ) -> None:
        """Binds at once (raises OSError if the port is taken); port 0 picks a free one. The thread runs
        under ``supervisor``'s rule (dc_core.supervision), a supervisor of its own when none is given."""
        self._server = _Server((listen, port), health, metrics, prometheus, logger, max_connections, timeout)
        host, bound_port = self._server.server_address[:2]
        self.address: tuple[str, int] = (str(host), int(bound_port))
        self.announcement: Path | None = None  # its file in the runtime folder, when written down
        self.supervisor = supervisor if supervisor is not None else Supervisor(_STDERR_LOGGER)
        self._thread = self.supervisor.start_thread(
            lambda: self._server.serve_forever(poll_interval=0.2), name="dc-status-http"
        )

    @property
    def refused(self) -> int:
        """Connections refused since start because ``max_connections`` were being served."""
        return self._server.refused

    def stop(self) -> None:
        withdraw(self.announcement)
        self.announcement = None
        self._server.shutdown()
        self._server.server_close()
        self._thread.join(timeout=2.0)


def start_status_server(
    logger: Logger,
    listen: str,
    port: int,
    *,
    health: Callable[[], bool | dict[str, Any]],
    metrics: Callable[[], dict[str, Any]],
    prometheus: Callable[[], str],
    supervisor: Supervisor | None = None,
    announce_as: tuple[str, int, str] | None = None,
) -> StatusServer | None:
    """A :class:`StatusServer`, its address logged; ``None`` (and a warning logged) if it cannot bind.

    Metrics are for operators: a taken port must not stop a server from doing its work. A port taken
    (another DC on this machine, in another ROS domain or namespace, has the same defaults) is a
    warning and the server serves on a free port instead. With ``announce_as`` (server name, ROS
    domain id, namespace) the address is written down for `dc status` (dc_core.metrics_registry)
    until :meth:`StatusServer.stop`.
    """

    def bind(at: int) -> StatusServer:
        return StatusServer(
            listen,
            at,
            health=health,
            metrics=metrics,
            prometheus=prometheus,
            logger=logger,
            supervisor=supervisor if supervisor is not None else Supervisor(logger),
        )

    try:
        try:
            server = bind(port)
        except OSError as exc:
            if exc.errno != errno.EADDRINUSE or port == 0:
                raise
            server = bind(0)
            logger.warning(
                f"metrics HTTP server: {listen}:{port} is taken (another DC on this machine?); serving on "
                f"{server.address[0]}:{server.address[1]} instead (dc status finds it)"
            )
    except OSError as exc:
        logger.warning(f"metrics HTTP server on {listen}:{port} not started, the server runs without it: {exc}")
        return None
    host, bound = server.address
    logger.info(f"metrics HTTP server on http://{host}:{bound}/api/v1/")
    if announce_as is not None:
        name, domain_id, namespace = announce_as
        # A wildcard listen is reached on loopback from this machine.
        reach = "127.0.0.1" if host in ("0.0.0.0", "") else "::1" if host == "::" else host
        server.announcement = announce(name, domain_id, namespace, reach, bound)
    return server


class PrometheusText:
    """Prometheus text exposition (format 0.0.4), one metric family at a time."""

    def __init__(self) -> None:
        self._lines: list[str] = []

    def family(self, name: str, kind: str, doc: str, samples: Sequence[tuple[str, float]]) -> None:
        """``samples`` are (labels, value); labels come from :func:`prometheus_labels` or are ``""``."""
        self._lines.append(f"# HELP {name} {doc}")
        self._lines.append(f"# TYPE {name} {kind}")
        for labels, value in samples:
            shown = f"{value:g}" if isinstance(value, float) else str(value)
            self._lines.append(f"{name}{labels} {shown}")

    def counter_table(
        self,
        prefix: str,
        label: str,
        rows: Mapping[str, Mapping[str, Any]],
        counters: Sequence[tuple[str, str, str]],
    ) -> None:
        """One family per ``(key, kind, help)`` of ``counters``, one sample per row that has the key.

        A counter is named ``<prefix>_<key>_total``, a gauge ``<prefix>_<key>``; each sample is
        labelled ``<label>="<row name>"``.
        """
        for key, kind, doc in counters:
            name = f"{prefix}_{key}_total" if kind == "counter" else f"{prefix}_{key}"
            samples = [
                (prometheus_labels(**{label: row}), values[key])
                for row, values in sorted(rows.items())
                if key in values
            ]
            if samples:
                self.family(name, kind, doc, samples)

    def text(self) -> str:
        return "\n".join(self._lines) + "\n"


def prometheus_labels(**labels: str) -> str:
    """``{key="value",...}`` with the values escaped as the text format requires."""
    return "{" + ",".join(f'{key}="{_escaped(value)}"' for key, value in labels.items()) + "}"


def _escaped(value: str) -> str:
    return value.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")
