"""The dashboard's HTTP server: one thread per connection, a bounded number of them, each socket timed out.

Each page opens one PostgreSQL connection, asks its bounded questions, renders, and closes it.
Anything a source cannot give becomes a sentence on the page (status 503), never a traceback.

A request whose ``Host`` is not one the dashboard is reached by gets 421: a web page elsewhere that
points its own host name at 127.0.0.1 (DNS rebinding) would otherwise read the dashboard, and
through it the database and the bucket, from the operator's browser.
"""

from __future__ import annotations

import datetime as dt
import socket
import sys
import time
from collections.abc import Callable, Iterable
from http.server import BaseHTTPRequestHandler
from typing import Any
from urllib.parse import parse_qs, urlsplit

from dc_core.http_limits import BoundedHTTPServer
from dc_dashboard import health, incidents, pages
from dc_dashboard.errors import DashboardError
from dc_dashboard.filters import Filters
from dc_dashboard.objects import ImageStore
from dc_dashboard.queries import Store
from dc_dashboard.settings import DashboardSettings

_SECURITY_HEADERS = {
    # Inline style and the two onchange handlers of the filters are the page's only code.
    "Content-Security-Policy": "default-src 'none'; img-src 'self'; style-src 'unsafe-inline'; "
    "script-src 'unsafe-inline'; form-action 'self'; frame-ancestors 'none'",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
}


class Dashboard:
    """What every request shares: the settings and the readers built from them."""

    def __init__(self, settings: DashboardSettings) -> None:
        self.settings = settings
        self.store = Store(settings.postgres)
        self.images = ImageStore(settings.s3)

    def source(self) -> str:
        pg = self.settings.postgres
        bucket = f" · S3 bucket {self.settings.s3.bucket}" if self.settings.s3.bucket else ""
        return f"PostgreSQL {pg.address()}, tables {pg.table} and {pg.files_table}{bucket}"

    def render(self, path: str, query: str) -> tuple[int, str]:
        """(HTTP status, HTML) of a page."""
        filters = Filters.parse(query)
        views: dict[str, tuple[str, Callable[[Any, Filters], str]]] = {
            "/": ("Overview: where the robot went", self._overview),
            "/system": ("System: CPU and memory", self._system),
            "/camera": ("Camera: inspected images and the codes read", self._camera),
            "/incidents": ("Incidents: what the recorders stored", self._incidents),
            "/files": ("Files: uploaded, verified, deleted", self._files),
            "/explore": ("Explorer: any measurement", self._explore),
            "/health": ("Health: DC's delivery", self._health),
            "/fleet": ("Fleet: every robot, last seen, failing destinations", self._fleet),
        }
        if path not in views:
            body = pages.error_body(f"no page {path}: see the navigation above")
            return 404, pages.layout(
                title="Not found", path=path, filters=filters, robots=[], runs=[], body=body, show_filters=False
            )
        title, view = views[path]
        robots: list[str] = []
        runs: list[str] = []
        try:
            with self.store.connection() as connection:
                robots = self.store.robots(connection)
                runs = self.store.runs(connection, filters.robot)
                body = view(connection, filters)
            status = 200
        except DashboardError as exc:
            body, status = pages.error_body(str(exc)), 503
            if path == "/health":  # the servers' metrics do not need PostgreSQL
                body += self._health(None, filters)
        return status, pages.layout(
            title=title,
            path=path,
            filters=filters,
            robots=robots,
            runs=runs,
            body=body,
            source=self.source(),
            show_filters=path != "/health",
        )

    def _overview(self, connection: Any, filters: Filters) -> str:
        trajectory = self.store.trajectory(connection, filters)
        distance = self.store.distance(connection, filters)
        catalog = self.store.catalog(connection)
        body = pages.overview(trajectory, distance, catalog.row_estimate, catalog.collected)
        if trajectory.map and trajectory.map.get("key"):
            problem = self.images.check_bucket()
            if problem:
                body = pages.notice(problem) + body
        return body

    def _system(self, connection: Any, filters: Filters) -> str:
        return pages.system(self.store.system(connection, filters), self.store.catalog(connection).collected)

    def _camera(self, connection: Any, filters: Filters) -> str:
        inspections, more = self.store.inspections(connection, filters)
        body = pages.camera(inspections, more, filters)
        problem = self.images.check_bucket() if inspections else None
        return (pages.notice(problem, element_id="s3-error") if problem else "") + body

    def _incidents(self, connection: Any, filters: Filters) -> str:
        found, more = incidents.incidents(self.store, connection, filters)
        body = incidents.page(found, more, filters)
        problem = self.images.check_bucket() if any(i.key for i in found) else None
        return (pages.notice(problem, element_id="s3-error") if problem else "") + body

    def _explore(self, connection: Any, filters: Filters) -> str:
        return pages.explore(self.store.explore(connection, filters), filters)

    def _files(self, connection: Any, filters: Filters) -> str:
        return pages.files(self.store.files(connection, filters), filters)

    def _fleet(self, connection: Any, filters: Filters) -> str:
        from dc_dashboard import fleet

        now = dt.datetime.now(dt.UTC).replace(tzinfo=None)
        rows, estimated = fleet.overview(self.store, connection, filters, now)
        return fleet.page(rows, now, estimated)

    def _health(self, connection: Any | None, filters: Filters) -> str:
        servers = [health.read(label, url) for label, url in self.settings.metrics]
        problems: list[str] = []
        last_stored: dict[str, Any] = {}
        storages: list[dict[str, Any]] = []
        missing: list[str] = []
        if connection is not None:
            last_stored = self.store.last_stored(connection)
            missing = self.store.catalog(connection).missing_indexes
            try:
                storages = self.store.files_by_storage(connection)
            except DashboardError as exc:  # no files table: DC delivers no files here
                problems.append(str(exc))
        return pages.health(servers, last_stored, storages, missing, problems, time.time())

    def image(self, query: str) -> tuple[int, bytes, str]:
        key = parse_qs(query).get("key", [""])[-1]
        try:
            body, content_type = self.images.image(key)
        except DashboardError as exc:
            return 404, f"{exc}\n".encode(), "text/plain; charset=utf-8"
        return 200, body, content_type


# Connections served at once: a few browser tabs, each loading a page and its images in parallel.
MAX_CONNECTIONS = 16
# Seconds a connection may stay silent while its request is read or its answer written (a page's
# queries are bounded apart, by the statement timeout).
REQUEST_TIMEOUT_S = 10.0


def allowed_hosts(listen: str, extra: Iterable[str] = ()) -> frozenset[str]:
    """The Host names a request may carry: the listening address, loopback's names, and ``extra``.

    Bound to every address (0.0.0.0, ::), the machine's own name is added too; any other name (a
    DNS name of the robot, a reverse proxy's) must be given.
    """
    names = {listen, "localhost", "127.0.0.1", "::1", *extra}
    if listen in ("0.0.0.0", "::", ""):
        names.add(socket.gethostname())
    return frozenset(normal_host(name) for name in names if name)


def normal_host(host: str) -> str:
    """A Host header (or a name) without its port and IPv6 brackets, lowercase, no trailing dot."""
    host = host.strip().lower()
    if host.startswith("["):  # [::1]:8088
        host = host[1 : host.find("]")] if "]" in host else host[1:]
    elif host.count(":") == 1:  # name:port; more colons: a bare IPv6 address
        host = host.split(":", 1)[0]
    return host.rstrip(".")


class Handler(BaseHTTPRequestHandler):
    server_version = "dc-dashboard"
    dashboard: Dashboard  # set on the subclass made by make_server
    hosts: frozenset[str] = frozenset()  # set on the subclass made by make_server
    quiet = False

    def do_GET(self) -> None:
        started = time.monotonic()
        url = urlsplit(self.path)
        host = self.headers.get("Host", "")
        try:
            if normal_host(host) not in self.hosts:
                # Not rendered: a rebinding page must learn nothing, not even whether PostgreSQL is up.
                status, content_type, extra = 421, "text/plain; charset=utf-8", {}
                body = (
                    f"421 this dashboard is not served as {host[:100]!r}: start it with --allowed-host NAME "
                    "for each name it is reached by\n"
                ).encode()
            elif url.path == "/image":
                status, body, content_type = self.dashboard.image(url.query)
                extra = {"Cache-Control": "private, max-age=3600"} if status == 200 else {}
            elif url.path == "/incident-file":
                if self._send_incident_file(url.query):
                    return
                status, body, content_type, extra = 404, b"no such incident file\n", "text/plain; charset=utf-8", {}
            elif url.path == "/favicon.ico":
                status, body, content_type, extra = 204, b"", "text/plain", {}
            else:
                status, html = self.dashboard.render(url.path, url.query)
                body, content_type, extra = html.encode(), "text/html; charset=utf-8", {"Cache-Control": "no-store"}
        except Exception as exc:  # a bug must not kill the thread silently nor show a traceback
            print(f"dc dashboard: {self.path}: {type(exc).__name__}: {exc}", file=sys.stderr)
            status, body, content_type, extra = 500, b"internal error (see the dashboard's log)\n", "text/plain", {}
        self.send_response(status)
        for name, value in {**_SECURITY_HEADERS, **extra}.items():
            self.send_header(name, value)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)
        if status == 421:  # said whatever `quiet` is: an operator with a new name must learn why
            self.log_message('"GET %s" 421: Host %r not allowed (--allowed-host)', url.path, host[:100])
        elif not self.quiet or status >= 500:
            self.log_message('"GET %s" %d %.0f ms', url.path, status, (time.monotonic() - started) * 1000)

    def _send_incident_file(self, query: str) -> bool:
        """Stream an incident's MCAP file from the bucket (never whole in memory); False: there is none to send."""
        key = parse_qs(query).get("key", [""])[-1]
        try:
            length, chunks = incidents.open_file(self.dashboard.images, key)
        except DashboardError as exc:
            self.log_message('"GET /incident-file" 404: %s', exc)
            return False
        self.send_response(200)
        for name, value in _SECURITY_HEADERS.items():
            self.send_header(name, value)
        self.send_header("Content-Type", "application/octet-stream")
        self.send_header("Content-Disposition", f'attachment; filename="{key.rsplit("/", 1)[-1]}"')
        self.send_header("Content-Length", str(length))
        self.end_headers()
        try:
            for chunk in chunks:
                self.wfile.write(chunk)
        except Exception as exc:  # the browser went away, or the bucket mid-file: the length tells it short
            self.log_message('"GET /incident-file" %s cut: %s: %s', key[:200], type(exc).__name__, exc)
            self.close_connection = True
        finally:
            chunks.close()
        return True

    def log_request(self, code: int | str = "-", size: int | str = "-") -> None:
        pass  # do_GET logs once, with the time taken

    def log_message(self, format: str, *args: Any) -> None:
        print(f"dc dashboard: {format % args}", file=sys.stderr)


def make_server(
    settings: DashboardSettings,
    host: str,
    port: int,
    quiet: bool = False,
    *,
    extra_hosts: Iterable[str] = (),
    max_connections: int = MAX_CONNECTIONS,
    timeout: float = REQUEST_TIMEOUT_S,
) -> BoundedHTTPServer:
    """``quiet``: log failed requests only; ``extra_hosts``: Host names allowed besides :func:`allowed_hosts`'."""
    handler = type(
        "DashboardHandler",
        (Handler,),
        {"dashboard": Dashboard(settings), "quiet": quiet, "hosts": allowed_hosts(host, extra_hosts)},
    )

    def refused(total: int) -> None:
        if total == 1 or total % 100 == 0:  # said, and then counted, not a line per refusal
            print(f"dc dashboard: {total} connections refused so far ({max_connections} being served)", file=sys.stderr)

    return BoundedHTTPServer(
        (host, port), handler, max_connections=max_connections, timeout=timeout, on_refused=refused
    )


def serve(
    settings: DashboardSettings,
    host: str,
    port: int,
    *,
    extra_hosts: Iterable[str] = (),
    max_connections: int = MAX_CONNECTIONS,
    timeout: float = REQUEST_TIMEOUT_S,
) -> int:
    try:
        server = make_server(
            settings, host, port, extra_hosts=extra_hosts, max_connections=max_connections, timeout=timeout
        )
    except OSError as exc:
        print(f"dc dashboard: cannot listen on {host}:{port}: {exc}", file=sys.stderr)
        return 2
    print(f"dc dashboard: http://{host}:{server.server_address[1]}/ (Ctrl-C stops it)", flush=True)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        server.server_close()
    return 0
