"""``dc servers run``: the local PostgreSQL, S3 (SeaweedFS) and InfluxDB, for trying DC and its demos.

They run in the foreground until Ctrl-C, on loopback, with their data under ``--state-dir``
(``var/dc/servers`` by default: a second run finds the same databases and objects). How to reach
them — ports, users, the generated passwords and keys — is written to ``<state-dir>/settings.yaml``
(readable by you only) rather than printed: the terminal's scrollback is no place for a password.
"""

from __future__ import annotations

import os
import secrets
import shlex
import threading
from pathlib import Path
from typing import Any

import yaml

from dc_bringup.local_servers import LocalServer, ServerError
from dc_bringup.local_servers.processes import free_port, port_free
from dc_core.signals import stop_on_signals

SERVER_NAMES = ("postgres", "s3", "influxdb", "nats")
# Started when no name is given; the NATS cluster is for the fleet path, asked for by name (docs/fleet.md).
DEFAULT_NAMES = ("postgres", "s3", "influxdb")
# Fixed ports (the usual ones plus 10000), so the demos' parameter files can name them; nats: the
# first of its three nodes' (14222, 14223, 14224).
DEFAULT_PORTS = {"postgres": 15432, "s3": 18333, "influxdb": 18086, "nats": 14222}


def make_server(name: str, state_dir: Path, port: int) -> LocalServer:
    if name == "postgres":
        from dc_bringup.local_servers.postgres import PostgresServer

        # A new password at each run (the role's is updated at start): settings.yaml has the current one.
        return PostgresServer(state_dir / name, port=port, password=secrets.token_urlsafe(16))
    if name == "s3":
        from dc_bringup.local_servers.seaweedfs import SeaweedS3Server

        return SeaweedS3Server(state_dir / name, port=port)
    if name == "influxdb":
        from dc_bringup.local_servers.influxdb import InfluxServer

        return InfluxServer(state_dir / name, port=port)
    if name == "nats":
        from dc_bringup.local_servers.nats import NatsCluster

        return NatsCluster(state_dir / name, port=port)
    raise ServerError(f"unknown server {name!r} (known: {', '.join(SERVER_NAMES)})")


def run(names: list[str], state_dir: Path, stop: threading.Event, say: Any = print) -> int:
    """Start ``names``, write their settings, wait for ``stop``, stop them (reverse order)."""
    started: list[tuple[str, LocalServer]] = []
    try:
        for name in names:
            port = DEFAULT_PORTS[name]
            if not port_free(port):  # a `dc demo` holds it, say: the settings written below name the one used
                say(f"{name}: port {port} is taken, using a free one")
                port = free_port()
            server = make_server(name, state_dir, port)
            server.start()
            started.append((name, server))
            say(f"{name}: listening on 127.0.0.1:{server.port}")
        settings = {name: server.settings() for name, server in started}
        env_file = state_dir / "servers.env"
        _write_private(env_file, environment_lines(settings))
        # Written last: its presence tells scripts and tests that the servers are up.
        settings_file = state_dir / "settings.yaml"
        _write_private(settings_file, yaml.safe_dump(settings, sort_keys=False))
        say(f"connection settings (passwords and keys included) in {settings_file} and {env_file}")
        say(f"for the demos: . {env_file}  (then dc-bringup params/demos/...); Ctrl-C stops the servers")
        stop.wait()
        return 0
    except ServerError as exc:
        say(f"dc servers: {exc}")
        return 2
    finally:
        for name, server in reversed(started):
            server.stop()
            say(f"{name}: stopped")


def environment(settings: dict[str, dict[str, Any]]) -> dict[str, str]:
    """``DC_<SERVER>_<KEY>`` for every setting: the names the demos' ``${...}`` references use."""
    return {f"DC_{name.upper()}_{key.upper()}": str(v) for name, keys in settings.items() for key, v in keys.items()}


def environment_lines(settings: dict[str, dict[str, Any]]) -> str:
    """:func:`environment` as shell ``export`` lines (servers.env)."""
    return "".join(f"export {name}={shlex.quote(value)}\n" for name, value in environment(settings).items())


def _write_private(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)


def main(args: Any) -> int:
    stop = stop_on_signals()  # handlers that take no lock (dc_core.signals)
    return run(list(args.names or DEFAULT_NAMES), Path(args.state_dir), stop)
