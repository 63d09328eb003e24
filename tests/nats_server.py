"""Real nats-server processes with JetStream on loopback for the NATS destination's and dc ingest's tests
(dc_bringup.local_servers.nats starts them), and what the tests read back from a stream."""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass
from typing import Any

from dc_bringup.local_servers.nats import INSTALL_HINT, NatsNode, nats_server_binary


def missing_reason() -> str | None:
    """Why the server or the client cannot run here (for pytest.skip), or None."""
    if nats_server_binary() is None:
        return INSTALL_HINT
    try:
        import nats  # noqa: F401
    except ImportError:
        return "nats-py is not installed (pip install 'ros2-dc[nats]')"
    return None


class NatsServer(NatsNode):
    """A :class:`NatsNode` running inside a ``with`` block."""

    def __enter__(self) -> NatsServer:
        self.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.stop()


@dataclass
class StoredMessage:
    subject: str
    data: bytes
    msg_id: str


async def settled_stream_info(js: Any, stream: str, timeout: float = 30.0) -> Any:
    """The stream's info once its cluster answers (a 503 while a restarted node catches up)."""
    import nats.js.errors

    deadline = time.monotonic() + timeout
    while True:
        try:
            return await js.stream_info(stream)
        except (nats.js.errors.ServiceUnavailableError, TimeoutError):
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.1)


async def _get_msg(js: Any, stream: str, seq: int, timeout: float = 30.0) -> Any:
    """A direct get, again while the cluster answers 503 (a leader elected after nodes came back)."""
    from nats.js.errors import ServiceUnavailableError

    deadline = time.monotonic() + timeout
    while True:
        try:
            return await js.get_msg(stream, seq)
        except ServiceUnavailableError:
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.2)


def read_stream(urls: list[str], stream: str, **auth: Any) -> list[StoredMessage]:
    """Every message the stream holds, in order (read with direct gets by sequence)."""

    async def read() -> list[StoredMessage]:
        import nats

        nc = await nats.connect(servers=urls, **auth)
        try:
            js = nc.jetstream()
            info = await settled_stream_info(js, stream)
            found = []
            for seq in range(info.state.first_seq, info.state.last_seq + 1):
                if seq == 0:
                    continue
                msg = await _get_msg(js, stream, seq)
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
            info = await settled_stream_info(nc.jetstream(), stream)
            return str(info.cluster.leader) if info.cluster and info.cluster.leader else ""
        finally:
            await nc.close()

    return asyncio.run(leader())
