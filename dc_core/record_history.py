"""A record topic's history bounded in bytes, not only in records (docs/delivery.md, "The history's memory").

DDS keeps, per writer, the last ``depth`` samples of a KEEP_LAST transient-local topic, serialised,
and sends all of them to every subscriber that joins late. Its depth is fixed when the writer is
created: no DDS policy bounds it in bytes. So :class:`SizedRecordPublisher` sizes the depth from
the largest record published so far, ``max(1, min(history_depth, history_bytes // largest))``, and
when a larger record makes the current depth too deep, it replaces the writer by one of the new
depth. The replacement waits for the new writer to be matched by the subscribers the old one had
(a volatile subscriber, group_server say, would miss what is published before it matched), but no
longer than it takes the old writer to hold ``history_bytes``: the bound is kept, not exceeded
while discovery runs. The old writer lives on until every record it holds is acknowledged by its
subscribers (checked at each publication), so during a replacement the two together hold at most
twice ``history_bytes``. The depth only ever shrinks (until the next configure).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

DEFAULT_HISTORY_BYTES = 64 * 1024 * 1024
"""Per output topic: 1,000 records of up to 64 KiB, or 64 records of 1 MiB (a map, a camera frame in base64)."""
# How long a new writer may wait to be matched by the old one's subscribers before it takes over
# (discovery between processes took ~0.35 s here; the start of collection waits 2 s the same way).
MATCH_WAIT_S = 2.0
# A replaced writer whose records are still not all acknowledged after this long is destroyed
# anyway: its subscriber is gone or stuck (what it lacked is the hand-off's to send again).
RETIRE_WAIT_S = 30.0


def history_depth_for(largest: int, history_depth: int, history_bytes: int) -> int:
    """The depth at which ``history_depth`` records of ``largest`` bytes fit in ``history_bytes`` (0: no bound)."""
    if history_bytes <= 0 or largest <= 0:
        return history_depth
    return max(1, min(history_depth, history_bytes // largest))


class _Writer:
    """One DDS writer, and the sizes of the records its history holds (its last ``depth``)."""

    def __init__(self, publisher: Any, depth: int) -> None:
        self.publisher = publisher
        self.depth = depth
        self.sizes: deque[int] = deque(maxlen=depth)
        self.held_bytes = 0
        self.retire_by = 0.0

    def publish(self, serialised: bytes) -> None:
        if len(self.sizes) == self.depth:
            self.held_bytes -= self.sizes[0]
        self.sizes.append(len(serialised))
        self.held_bytes += len(serialised)
        self.publisher.publish(serialised)

    def bytes_with(self, size: int) -> int:
        """What the history would hold with one more record of ``size`` bytes."""
        return self.held_bytes + size - (self.sizes[0] if len(self.sizes) == self.depth else 0)


class SizedRecordPublisher:
    """A record topic's publisher whose DDS history holds at most ``history_bytes`` (see the module documentation).

    ``create(depth)`` makes a (lifecycle) publisher of the topic with that history depth,
    ``destroy(publisher)`` releases one. ``publish`` takes serialised records; it may be called
    from any thread.
    """

    def __init__(
        self,
        topic: str,
        create: Callable[[int], Any],
        destroy: Callable[[Any], object],
        *,
        history_depth: int,
        history_bytes: int,
        record_bytes_estimate: int | None = None,
        logger: Any = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.topic = topic
        self._create = create
        self._destroy = destroy
        self.history_depth = history_depth
        self.history_bytes = history_bytes
        self._logger = logger
        self._clock = clock
        self._lock = threading.Lock()
        self.largest = 0
        self._active = False
        # A plugin's estimate of its records spares the first replacement (and its discovery) when right.
        depth = history_depth_for(record_bytes_estimate or 0, history_depth, history_bytes)
        self._current = _Writer(create(depth), depth)
        self._pending: _Writer | None = None
        self._pending_since = 0.0
        self._retired: list[_Writer] = []
        self.replaced = 0

    # -- what the server calls ----------------------------------------------------------------
    @property
    def depth(self) -> int:
        """The depth of the newest writer (the one taking over, during a replacement)."""
        with self._lock:
            return (self._pending or self._current).depth

    def get_subscription_count(self) -> int:
        with self._lock:
            return int(self._current.publisher.get_subscription_count())

    def on_activate(self, state: Any) -> None:
        with self._lock:
            self._active = True
            for writer in self._writers():
                writer.publisher.on_activate(state)

    def on_deactivate(self, state: Any) -> None:
        with self._lock:
            self._active = False
            for writer in self._writers():
                writer.publisher.on_deactivate(state)

    def destroy(self) -> None:
        """Release every writer (at cleanup)."""
        with self._lock:
            for writer in self._writers():
                self._destroy(writer.publisher)
            self._pending = None
            self._retired.clear()

    def held_bytes(self) -> int:
        """Bytes of the records the histories of this topic's writers hold now (retired ones included)."""
        with self._lock:
            return sum(writer.held_bytes for writer in self._writers())

    def publish(self, serialised: bytes) -> None:
        size = len(serialised)
        with self._lock:
            if size > self.largest:
                self.largest = size
                self._resize(history_depth_for(size, self.history_depth, self.history_bytes))
            pending = self._pending
            if pending is not None and self._takes_over(pending, size):
                self._current.retire_by = self._clock() + RETIRE_WAIT_S
                self._retired.append(self._current)
                self._current, self._pending = pending, None
            self._current.publish(serialised)
            if self._retired:
                self._release_retired()

    # -- inside --------------------------------------------------------------------------------
    def _writers(self) -> list[_Writer]:
        return [self._current, *([self._pending] if self._pending is not None else []), *self._retired]

    def _resize(self, depth: int) -> None:
        newest = self._pending or self._current
        if depth >= newest.depth:
            return
        if self._pending is not None:  # never published into: replaced by a shallower one at once
            self._destroy(self._pending.publisher)
        publisher = self._create(depth)
        if self._active:
            publisher.on_activate(None)
        self._pending = _Writer(publisher, depth)
        self._pending_since = self._clock()
        self.replaced += 1
        if self._logger is not None:
            self._logger.info(
                f"{self.topic}: records of {self.largest} bytes: history depth {depth} "
                f"(history_bytes {self.history_bytes}), was {newest.depth}"
            )

    def _takes_over(self, pending: _Writer, size: int) -> bool:
        current = self._current
        # The bound first: the old writer would hold more than the new one may (a single record larger
        # than history_bytes is held by either).
        if current.bytes_with(size) > max(self.history_bytes, size):
            return True
        if self._clock() - self._pending_since >= MATCH_WAIT_S:
            return True
        return bool(pending.publisher.get_subscription_count() >= current.publisher.get_subscription_count())

    def _release_retired(self) -> None:
        from rclpy.duration import Duration

        now = self._clock()
        keep = []
        for writer in self._retired:
            if now < writer.retire_by and not writer.publisher.wait_for_all_acked(Duration(seconds=0)):
                keep.append(writer)
            else:
                self._destroy(writer.publisher)
        self._retired = keep


def history_metrics(publishers: list[SizedRecordPublisher]) -> dict[str, dict[str, int]]:
    """Per output topic: the history's depth, the largest record, the bytes held, the writers replaced."""
    return {
        publisher.topic: {
            "depth": publisher.depth,
            "largest_record": publisher.largest,
            "held_bytes": publisher.held_bytes(),
            "replaced": publisher.replaced,
        }
        for publisher in publishers
    }
