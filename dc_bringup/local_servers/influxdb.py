"""A throw-away InfluxDB 1.x on loopback, for the InfluxDB destination's tests and for trying DC (`dc servers start`).

Debian's ``influxdb`` package (1.6) is the server that installs here: it offers the v1 HTTP API
(``/write``, ``/query``), which is what the destination writes to by default. The server's meta,
data and WAL folders, its configuration, log, pid and port live in the state folder, so a restart
with the same folder finds the same data on the same port. Usage reporting and the ``_internal``
monitoring database are off; with ``user`` set, authentication is on and that user is an admin.
With ``tls`` (certificate, key and the CA that signed it, PEM files) it answers HTTPS only.
"""

from __future__ import annotations

import base64
import contextlib
import json
import shutil
import ssl
import subprocess
import time
import urllib.error
import urllib.parse
import urllib.request
from pathlib import Path

from dc_bringup.local_servers import ServerError
from dc_bringup.local_servers.processes import (
    free_port,
    log_tail,
    pid_from_file,
    port_of_last_start,
    remember_port,
    stop_server,
)

INSTALL_HINT = "InfluxDB is not installed (apt install influxdb)"


def missing_reason() -> str | None:
    """Why an InfluxServer cannot run here, or None."""
    return None if shutil.which("influxd") else INSTALL_HINT


class InfluxServer:
    """InfluxDB 1.x with one database (and optionally one admin user) on 127.0.0.1."""

    name = "influxdb"

    def __init__(
        self,
        state_dir: Path,
        port: int = 0,
        database: str = "dc",
        user: str = "",
        password: str = "",
        tls: tuple[Path, Path, Path] | None = None,
    ) -> None:
        self.state_dir = Path(state_dir).absolute()
        self.tls = tls
        # How this process checks the server it started: with the CA of its certificate.
        self._client_tls = ssl.create_default_context(cafile=str(tls[2])) if tls is not None else None
        self.database = database
        self.user = user
        self.password = password
        self.port = port_of_last_start(self.state_dir, port)
        self._process: subprocess.Popen[bytes] | None = None

    def __repr__(self) -> str:  # without the password
        return f"InfluxServer({str(self.state_dir)!r}, port={self.port}, database={self.database!r})"

    @property
    def log_file(self) -> Path:
        return self.state_dir / "influxd.log"

    @property
    def url(self) -> str:
        return f"{'https' if self.tls is not None else 'http'}://127.0.0.1:{self.port}"

    # -- protocol ---------------------------------------------------------------------------------
    def start(self, timeout: float = 30.0) -> None:
        influxd = shutil.which("influxd")
        if influxd is None:
            raise ServerError(INSTALL_HINT)
        deadline = time.monotonic() + timeout
        if not self.running():
            self.state_dir.mkdir(parents=True, exist_ok=True)
            config = self._write_config()
            remember_port(self.state_dir, self.port)
            with self.log_file.open("ab") as log:
                # A session of its own: a Ctrl-C in the terminal that ran `dc servers start` does not reach it.
                self._process = subprocess.Popen(
                    [influxd, "-config", str(config)],
                    stdin=subprocess.DEVNULL,
                    stdout=log,
                    stderr=subprocess.STDOUT,
                    start_new_session=True,
                )
            (self.state_dir / "influxd.pid").write_text(f"{self._process.pid}\n")
        self._wait_ready(deadline)
        self._create_user_and_database()

    def stop(self, timeout: float = 10.0) -> None:
        stop_server(self.state_dir / "influxd.pid", self._process, timeout)
        self._process = None

    def running(self) -> bool:
        return self._pid() is not None

    def settings(self) -> dict[str, str | int]:
        values: dict[str, str | int] = {"host": "127.0.0.1", "port": self.port, "database": self.database}
        if self.user:
            values.update(http_user=self.user, http_passwd=self.password)
        if self.tls is not None:
            values.update(tls="true", tls_ca_file=str(self.tls[2]))
        return values

    def __enter__(self) -> InfluxServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- queries -----------------------------------------------------------------------------------
    def query(
        self, statement: str, *, database: str = "", post: bool = False, authenticate: bool = True
    ) -> list[dict[str, object]]:
        """Run InfluxQL through /query (as the admin when auth is on); the ``results`` of the answer.

        Times come back in nanoseconds since the epoch (``epoch=ns``)."""
        fields = {"q": statement, "epoch": "ns", **({"db": database} if database else {})}
        encoded = urllib.parse.urlencode(fields)
        if post:
            request = urllib.request.Request(f"{self.url}/query", data=encoded.encode(), method="POST")
            request.add_header("Content-Type", "application/x-www-form-urlencoded")
        else:
            request = urllib.request.Request(f"{self.url}/query?{encoded}")
        if self.user and authenticate:
            token = base64.b64encode(f"{self.user}:{self.password}".encode()).decode("ascii")
            request.add_header("Authorization", f"Basic {token}")
        try:
            with urllib.request.urlopen(request, timeout=10, context=self._client_tls) as response:
                answer = json.loads(response.read())
        except urllib.error.HTTPError as exc:
            raise ServerError(
                f"InfluxDB refused {statement.split()[0]}: HTTP {exc.code} {exc.read()[:200]!r}"
            ) from None
        results: list[dict[str, object]] = answer.get("results", [])
        for result in results:
            if "error" in result:
                raise ServerError(f"InfluxDB: {result['error']}")
        return results

    # -- helpers ----------------------------------------------------------------------------------
    def _write_config(self) -> Path:
        rpc_port_file = self.state_dir / "rpc_port"
        # The backup/restore RPC port (8088 by default) must not collide with another server either.
        rpc_port = int(rpc_port_file.read_text()) if rpc_port_file.is_file() else free_port()
        rpc_port_file.write_text(f"{rpc_port}\n")
        text = f"""# Written by DC's local server at each start.
reporting-disabled = true
bind-address = "127.0.0.1:{rpc_port}"

[meta]
  dir = {json.dumps(str(self.state_dir / "meta"))}

[data]
  dir = {json.dumps(str(self.state_dir / "data"))}
  wal-dir = {json.dumps(str(self.state_dir / "wal"))}
  query-log-enabled = false

[monitor]
  store-enabled = false

[http]
  bind-address = "127.0.0.1:{self.port}"
  auth-enabled = {"true" if self.user else "false"}
  log-enabled = false
"""
        if self.tls is not None:
            certificate, key, _ca = self.tls
            text += f"""  https-enabled = true
  https-certificate = {json.dumps(str(certificate))}
  https-private-key = {json.dumps(str(key))}
"""
        path = self.state_dir / "influxdb.conf"
        path.write_text(text)
        return path

    def _wait_ready(self, deadline: float) -> None:
        while True:
            if self._process is not None and self._process.poll() is not None:
                raise ServerError(
                    f"influxd exited with status {self._process.returncode} on port {self.port}{self._log_tail()}"
                )
            try:
                with urllib.request.urlopen(f"{self.url}/ping", timeout=2, context=self._client_tls) as response:
                    if response.status == 204:
                        return
            except (OSError, urllib.error.URLError):
                pass
            if time.monotonic() > deadline:
                raise ServerError(f"InfluxDB on port {self.port} did not answer /ping{self._log_tail()}")
            time.sleep(0.05)

    def _create_user_and_database(self) -> None:
        if self.user:
            statement = f"CREATE USER {_ident(self.user)} WITH PASSWORD {_literal(self.password)} WITH ALL PRIVILEGES"
            # With auth on and no admin yet, InfluxDB lets anyone create the first admin; once one
            # exists (a restart), this fails and CREATE DATABASE below checks the password instead.
            with contextlib.suppress(ServerError):
                self.query(statement, post=True, authenticate=False)
        self.query(f"CREATE DATABASE {_ident(self.database)}", post=True)  # a no-op when it exists

    def _pid(self) -> int | None:
        return pid_from_file(self.state_dir / "influxd.pid")

    def _log_tail(self) -> str:
        return log_tail(self.log_file)


def _ident(name: str) -> str:
    return '"' + name.replace("\\", "\\\\").replace('"', '\\"') + '"'


def _literal(text: str) -> str:
    return "'" + text.replace("\\", "\\\\").replace("'", "\\'") + "'"
