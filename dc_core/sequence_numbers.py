"""The DDS writers of one topic, told apart by their publication sequence numbers.

Each DDS writer numbers its samples 1, 2, 3, ..., and rclpy hands the number to a subscription
callback that takes MessageInfo: a jump in one writer's numbers is records that never arrived.
rclpy gives no publisher id, so the writers of a topic are told apart by the numbers themselves.
Pure: no ROS, no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

MAX_WRITERS_PER_TOPIC = 8


@dataclass
class _Writer:
    last_seq: int
    last_used: int


class TopicWriters:
    """The publishers of one topic, recognised by their sequence numbers; counts the numbers skipped.

    A record continues the writer whose last number is the highest one below its own (ties go to
    the writer heard from last); a record below every known writer's last number starts a new
    writer — a publisher that restarted numbers from 1 again. With one publisher per topic (each
    of DC's topics has one) this is exact. With several, told apart while their numbers stay
    apart; once two of them reach the same number, a record can be taken for the other's, which
    shows as a gap that was none (or hides one): the counts are then approximate.
    """

    def __init__(self, max_writers: int = MAX_WRITERS_PER_TOPIC) -> None:
        self._max_writers = max_writers
        self._writers: list[_Writer] = []
        self._clock = 0

    def observe(self, seq: int) -> int | None:
        """Numbers skipped before ``seq`` by its writer (0 in order), or ``None`` for a new writer."""
        self._clock += 1
        best: _Writer | None = None
        for writer in self._writers:
            if writer.last_seq < seq and (
                best is None or (writer.last_seq, writer.last_used) > (best.last_seq, best.last_used)
            ):
                best = writer
        if best is None:
            if len(self._writers) >= self._max_writers:
                self._writers.remove(min(self._writers, key=lambda w: w.last_used))
            self._writers.append(_Writer(seq, self._clock))
            return None
        skipped = seq - best.last_seq - 1
        best.last_seq = seq
        best.last_used = self._clock
        return skipped

    @property
    def count(self) -> int:
        return len(self._writers)
