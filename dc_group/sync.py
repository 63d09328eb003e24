"""DC's approximate-time synchroniser: one message per input whose stamps lie within a slop.

Pure and clock-injected: the caller passes ``now`` (seconds on any monotonic clock) to
:meth:`ApproximateTimeSync.offer` and :meth:`ApproximateTimeSync.expire`, so tests need no sleeps.

Rules (each one is what a user of a group can rely on):

- Every input keeps its pending messages sorted by stamp, so arrival order does not matter.
- A complete set is emitted as soon as one exists: when a message arrives, the set that contains it
  and one pending message of every other input with the smallest spread (latest stamp minus
  earliest) not above the slop is emitted; equal spreads prefer the later stamps.
- Emitting a set (complete or not) consumes its messages and *supersedes* every pending message of
  the same inputs stamped at or before the ones used: a newer message of that input went out.
  A message arriving later stamped at or before the last one used from its input is *late* and
  discarded, so the stamps published for one input never go backwards.
- A pending message that has waited ``timeout`` seconds (from its arrival, on the injected clock)
  anchors an incomplete set: the anchor plus the best pending partners within the slop of it (most
  inputs present, then smallest spread, then latest stamps). :meth:`expire` returns such sets; the
  caller drops or publishes them. A silent input therefore never blocks the group.
- Each input's queue holds at most ``queue_size`` pending messages; beyond that the one with the
  oldest stamp is discarded (*overflowed*), the least likely to ever be matched.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Generic, TypeVar

T = TypeVar("T")


@dataclass(frozen=True)
class Pending(Generic[T]):
    """One message waiting to be synchronised."""

    input_index: int
    stamp_ns: int
    arrival: float
    seq: int
    payload: T

    @property
    def order(self) -> tuple[int, int]:
        return (self.stamp_ns, self.seq)


@dataclass(frozen=True)
class SyncedSet(Generic[T]):
    """Messages that belong together: one per input, ``None`` where an input is missing."""

    members: tuple[Pending[T] | None, ...]

    @property
    def present(self) -> list[Pending[T]]:
        return [m for m in self.members if m is not None]

    @property
    def missing(self) -> tuple[int, ...]:
        return tuple(i for i, m in enumerate(self.members) if m is None)

    @property
    def complete(self) -> bool:
        return all(m is not None for m in self.members)

    @property
    def stamp_ns(self) -> int:
        """The synchronised stamp: the latest stamp of the set."""
        return max(m.stamp_ns for m in self.present)

    @property
    def spread_ns(self) -> int:
        stamps = [m.stamp_ns for m in self.present]
        return max(stamps) - min(stamps)


@dataclass
class SyncCounters:
    """Where every offered message went."""

    complete_sets: int = 0
    incomplete_sets: int = 0
    superseded: int = 0
    late: int = 0
    overflowed: int = 0


@dataclass
class _InputQueue(Generic[T]):
    pending: list[Pending[T]] = field(default_factory=list)
    last_used_stamp_ns: int | None = None


class ApproximateTimeSync(Generic[T]):
    """Matches messages of ``input_count`` inputs by stamp; see the module documentation."""

    def __init__(self, input_count: int, *, slop_ns: int, timeout: float, queue_size: int) -> None:
        if input_count < 1:
            raise ValueError("a synchroniser needs at least one input")
        if slop_ns < 0 or timeout <= 0 or queue_size < 1:
            raise ValueError("slop must be >= 0, timeout > 0 and queue_size >= 1")
        self.input_count = input_count
        self.slop_ns = slop_ns
        self.timeout = timeout
        self.queue_size = queue_size
        self.counters = SyncCounters()
        self._queues: list[_InputQueue[T]] = [_InputQueue() for _ in range(input_count)]
        self._seq = 0

    # -- public ------------------------------------------------------------------------------
    def offer(self, input_index: int, stamp_ns: int, payload: T, now: float) -> SyncedSet[T] | None:
        """Add a message; return the complete set it completes, if any."""
        queue = self._queues[input_index]
        if queue.last_used_stamp_ns is not None and stamp_ns <= queue.last_used_stamp_ns:
            self.counters.late += 1
            return None
        self._seq += 1
        message = Pending(input_index, stamp_ns, now, self._seq, payload)
        bisect.insort(queue.pending, message, key=lambda p: p.order)
        best = self._best_set_around(message)
        if best.complete:
            self._consume(best)
            self.counters.complete_sets += 1
            return best
        if len(queue.pending) > self.queue_size:
            queue.pending.pop(0)
            self.counters.overflowed += 1
        return None

    def expire(self, now: float) -> list[SyncedSet[T]]:
        """Incomplete sets whose oldest message has waited ``timeout``, oldest first."""
        out: list[SyncedSet[T]] = []
        while True:
            anchor = self._first_arrived()
            if anchor is None or now - anchor.arrival < self.timeout:
                return out
            incomplete = self._best_set_around(anchor)
            self._consume(incomplete)
            self.counters.incomplete_sets += 1
            out.append(incomplete)

    def flush(self) -> list[SyncedSet[T]]:
        """Every pending message as incomplete sets (at deactivation)."""
        return self.expire(math.inf)

    def pending_count(self) -> int:
        return sum(len(q.pending) for q in self._queues)

    def next_deadline(self) -> float | None:
        """When the next incomplete set is due (injected clock), or None with nothing pending."""
        anchor = self._first_arrived()
        return None if anchor is None else anchor.arrival + self.timeout

    # -- matching ----------------------------------------------------------------------------
    def _first_arrived(self) -> Pending[T] | None:
        heads = [min(q.pending, key=lambda p: (p.arrival, p.seq)) for q in self._queues if q.pending]
        return min(heads, key=lambda p: (p.arrival, p.seq)) if heads else None

    def _best_set_around(self, anchor: Pending[T]) -> SyncedSet[T]:
        """The best set containing ``anchor``: most inputs, then smallest spread, then latest.

        Every candidate window is ``[low, low + slop]`` where ``low`` is a pending stamp not after
        the anchor and not more than the slop before it; in a window each other input contributes
        its earliest message, which minimises the latest stamp and so the spread.
        """
        t = anchor.stamp_ns
        lows = {t}
        for queue in self._queues:
            for p in queue.pending:
                if t - self.slop_ns <= p.stamp_ns <= t:
                    lows.add(p.stamp_ns)
        best: SyncedSet[T] | None = None
        best_score: tuple[int, int, int, int] | None = None
        for low in sorted(lows):
            members = self._window(anchor, low, low + self.slop_ns)
            candidate = SyncedSet(members)
            present = candidate.present
            score = (
                len(present),
                -candidate.spread_ns,
                max(m.stamp_ns for m in present),
                min(m.stamp_ns for m in present),
            )
            if best_score is None or score > best_score:
                best, best_score = candidate, score
        assert best is not None  # lows always holds the anchor's own stamp
        return best

    def _window(self, anchor: Pending[T], low: int, high: int) -> tuple[Pending[T] | None, ...]:
        members: list[Pending[T] | None] = []
        for index, queue in enumerate(self._queues):
            if index == anchor.input_index:
                members.append(anchor)
                continue
            members.append(_earliest_in(queue.pending, low, high))
        return tuple(members)

    def _consume(self, synced: SyncedSet[T]) -> None:
        for used in synced.present:
            queue = self._queues[used.input_index]
            kept = [p for p in queue.pending if p.stamp_ns > used.stamp_ns]
            # The used message itself is removed too; the others stamped at or before it are superseded.
            self.counters.superseded += len(queue.pending) - len(kept) - 1
            queue.pending = kept
            queue.last_used_stamp_ns = used.stamp_ns


def _earliest_in(pending: Sequence[Pending[T]], low: int, high: int) -> Pending[T] | None:
    index = bisect.bisect_left(pending, (low, -1), key=lambda p: p.order)
    if index < len(pending) and pending[index].stamp_ns <= high:
        return pending[index]
    return None
