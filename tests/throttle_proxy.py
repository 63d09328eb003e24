"""A TCP proxy on loopback that plays a poor link: a rate, a latency, outages; it logs what it carries.

asyncio in a thread of the test process. Between DC and a real receiver, it stands for the LTE link of
docs/constrained_links.md: what DC sent upstream, and when, is in :attr:`ThrottleProxy.upstream`.
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
import time
from types import TracebackType


class ThrottleProxy:
    """Forwards 127.0.0.1:<port> to ``target``; ``rate`` bytes/s each way (None: as fast as it goes),
    ``latency`` seconds added to each chunk, :meth:`cut` drops every connection and refuses new ones."""

    def __init__(self, target: tuple[str, int], *, rate: float | None = None, latency: float = 0.0) -> None:
        self.target = target
        self.rate = rate
        self.latency = latency
        self.port = 0
        self.upstream: list[tuple[float, int]] = []  # (time.monotonic(), bytes) of each chunk passed to target
        self._down = False
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, daemon=True)
        self._server: asyncio.base_events.Server | None = None
        self._writers: set[asyncio.StreamWriter] = set()
        self._lock = threading.Lock()

    def __enter__(self) -> ThrottleProxy:
        self._thread.start()
        self._server = asyncio.run_coroutine_threadsafe(
            asyncio.start_server(self._accept, "127.0.0.1", 0), self._loop
        ).result(5)
        self.port = int(self._server.sockets[0].getsockname()[1])
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        asyncio.run_coroutine_threadsafe(self._close(), self._loop).result(5)
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(5)

    def cut(self) -> None:
        """The link goes away: open connections reset, new ones closed at once."""
        self._down = True
        asyncio.run_coroutine_threadsafe(self._drop_all(), self._loop).result(5)

    def restore(self) -> None:
        self._down = False

    def sent_between(self, start: float, end: float) -> int:
        with self._lock:
            return sum(n for t, n in self.upstream if start <= t < end)

    async def _close(self) -> None:
        if self._server is not None:
            self._server.close()
        await self._drop_all()
        # The connections' tasks end here, not with a warning when the loop is collected.
        others = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
        for task in others:
            task.cancel()
        await asyncio.gather(*others, return_exceptions=True)

    async def _drop_all(self) -> None:
        for writer in list(self._writers):
            with contextlib.suppress(Exception):
                writer.transport.abort()
        self._writers.clear()

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if self._down:
            writer.transport.abort()
            return
        try:
            up_reader, up_writer = await asyncio.open_connection(*self.target)
        except OSError:
            writer.transport.abort()
            return
        self._writers.update((writer, up_writer))
        await asyncio.gather(
            self._pipe(reader, up_writer, count=True),
            self._pipe(up_reader, writer, count=False),
            return_exceptions=True,
        )
        for w in (writer, up_writer):
            self._writers.discard(w)
            w.transport.abort()

    async def _pipe(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, *, count: bool) -> None:
        while not self._down:
            chunk = await reader.read(4096)
            if not chunk:
                break
            if self.latency:
                await asyncio.sleep(self.latency)
            if self.rate:
                await asyncio.sleep(len(chunk) / self.rate)
            if self._down:
                break
            writer.write(chunk)
            await writer.drain()
            if count:
                with self._lock:
                    self.upstream.append((time.monotonic(), len(chunk)))
        with contextlib.suppress(Exception):
            writer.transport.abort()
