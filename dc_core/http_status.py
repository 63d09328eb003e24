"""Health and metrics of a DC server over HTTP, the paths Fluent Bit users know (``/api/v1/...``).

Standard library only; one daemon thread serving requests one at a time, which is plenty for a
scraper and an operator. Bound to loopback unless ``http_listen`` says otherwise. Each server
brings its own documents; :class:`PrometheusText` writes its counters in the text format.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Callable, Mapping, Sequence
from http.server import BaseHTTPRequestHandler, HTTPServer
from typing import Any

from dc_core.logs import Logger


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
                self._reply(200, "application/json", json.dumps(self.server.metrics(), indent=2))
            elif path == "/api/v1/metrics/prometheus":
                self._reply(200, "text/plain; version=0.0.4; charset=utf-8", self.server.prometheus())
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


class _Server(HTTPServer):
    def __init__(
        self,
        address: tuple[str, int],
        health: Callable[[], bool | dict[str, Any]],
        metrics: Callable[[], dict[str, Any]],
        prometheus: Callable[[], str],
    ) -> None:
        self.health = health
        self.metrics = metrics
        self.prometheus = prometheus
        super().__init__(address, _Handler)


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
    ) -> None:
        """Binds at once (raises OSError if the port is taken); port 0 picks a free one."""
        self._server = _Server((listen, port), health, metrics, prometheus)
        host, bound_port = self._server.server_address[:2]
        self.address: tuple[str, int] = (str(host), int(bound_port))
        self._thread = threading.Thread(
            target=self._server.serve_forever,
            kwargs={"poll_interval": 0.2},
            name="dc-status-http",
            daemon=True,
        )
        self._thread.start()

    def stop(self) -> None:
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
) -> StatusServer | None:
    """A :class:`StatusServer`, its address logged; ``None`` (and an error logged) if it cannot bind.

    Metrics are for operators: a taken port must not stop a server from doing its work.
    """
    try:
        server = StatusServer(listen, port, health=health, metrics=metrics, prometheus=prometheus)
    except OSError as exc:
        logger.error(f"metrics HTTP server on {listen}:{port} not started: {exc}")
        return None
    host, bound = server.address
    logger.info(f"metrics HTTP server on http://{host}:{bound}/api/v1/")
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
