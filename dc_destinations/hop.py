"""The DDS hop into destination_server: recognise replayed records, count records lost on the way.

DC's own servers publish records with a transient-local history (dc_core.qos), so a
destination_server that (re)starts receives each publisher's last records again. A record is
known by its :class:`HopKey` — topic, the publisher's source timestamp and its DDS publication
sequence number, which a replay repeats unchanged — and the keys of records already handled are
kept in the delivery buffer, committed with the records themselves. A replayed record whose key
is there is a duplicate and is dropped before routing.

Sequence numbers also show what never arrived: a jump from 5,000 to 7,001 means 2,000 records
were lost between the publisher and this server (dropped by DDS under a flood, or published while
the server was down, beyond the history); :class:`dc_core.sequence_numbers.TopicWriters` counts
them.

Records of DC's own publishers carry a hand-off key in ``header.frame_id`` (dc_core.handoff): their
hop key is then ``(topic, -publisher id, the publisher's own number)``, which a record sent again
keeps (DDS would number it anew), and what is lost is what the publisher dropped unacknowledged:
numbers below its ``low`` that never arrived, and, when the publisher's process ended (killed) holding
records, the numbers up to where it got that never arrived, announced by its successor
(dc_core.handoff_marks, :meth:`HopIntake.writer_ended`). Pure: no ROS, no I/O.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any, NamedTuple

from dc_core.handoff import ENDED_SUFFIX, SETTLED_SUFFIX, SOURCE_SUFFIX, parse_frame_key, position_topic
from dc_core.sequence_numbers import MAX_WRITERS_PER_TOPIC, TopicWriters


class HopKey(NamedTuple):
    """What identifies one published record: a replay of it carries the same three values.

    A plain tuple, so the buffer stores it without knowing this module.
    """

    topic: str
    source_ns: int
    seq: int


class HopLosses(NamedTuple):
    """Records of ``topic`` counted lost (``missing``; negative: some arrived after all) in ``gaps``
    jumps since the last hand-over, for the buffer's lifetime totals (added by the group commit)."""

    topic: str
    missing: int
    gaps: int


def hop_key(topic: str, info: Mapping[str, Any] | None) -> HopKey | None:
    """The key of a received record from rclpy's MessageInfo; ``None`` when the middleware gave none.

    Without a source timestamp or a sequence number two different records could share a key, and
    dropping one of them as a duplicate would lose it: such records are not deduplicated at all.
    """
    if not info:
        return None
    source_ns = info.get("source_timestamp")
    seq = info.get("publication_sequence_number")
    if not isinstance(source_ns, int) or not isinstance(seq, int) or source_ns <= 0 or seq <= 0:
        return None
    return HopKey(topic, source_ns, seq)


def keyed_hop_key(topic: str, frame_id: str) -> tuple[HopKey, int, int] | None:
    """The hop key of a record with a hand-off key, its publisher's ``low`` and source number; None without one."""
    parsed = parse_frame_key(frame_id) if frame_id else None
    if parsed is None:
        return None
    writer, seq, low, source = parsed
    return HopKey(topic, -writer, seq), low, source


def source_key(key: HopKey, source: int) -> HopKey:
    """The key that keeps, in the buffer, the highest source number forwarded by ``key``'s publisher."""
    return HopKey(key.topic + SOURCE_SUFFIX, key.source_ns, source)


@dataclass(frozen=True)
class Verdict:
    """What the hop says of one arriving record."""

    duplicate: bool = False
    skipped: int = 0  # records of the same writer that never arrived just before this one
    first_skipped: int = 0  # sequence number of the first of them
    new_writer: bool = False
    source: bool = False  # the skipped numbers are the source's (records a restarted publisher never forwarded)


# The verdicts of most records, made once: a frozen dataclass costs ~1 us to build, per record.
_NOTHING_TO_SAY = Verdict()
_DUPLICATE = Verdict(duplicate=True)
_NEW_WRITER = Verdict(new_writer=True)


@dataclass
class TopicHopStats:
    received: int = 0
    duplicates: int = 0
    missing: int = 0  # records known lost: sequence numbers skipped
    gaps: int = 0  # how many jumps those were
    writers: int = 0  # writers recognised since start (a restarted publisher is a new one)
    unkeyed: int = 0  # records without a source timestamp or sequence number: not deduplicated
    # Hand-off publishers whose process ended holding records not acknowledged, as their successor
    # announced them; what of theirs never arrived is in ``missing``.
    writers_ended: int = 0


@dataclass
class _Keyed:
    """One hand-off publisher: every number below ``settled`` was handled or counted lost."""

    settled: int
    above: set[int] = field(default_factory=set)  # handled numbers at or above settled
    used: int = 0
    # Ranges counted as missing: (first, last, the numbers in it handled before, those arrived since).
    counted: list[tuple[int, int, set[int], set[int]]] = field(default_factory=list)


# Ranges counted as missing remembered per publisher, so that a record of one arriving late (the
# publisher dropped it while it was still on its way) is taken off the count again.
COUNTED_RANGES = 64


@dataclass
class _TopicState:
    writers: TopicWriters
    keyed: dict[int, _Keyed] = field(default_factory=dict)
    # Per hand-off publisher the highest source number it forwarded (StringStamped: your node's).
    source_max: dict[int, int] = field(default_factory=dict)
    seen: set[HopKey] = field(default_factory=set)
    order: deque[HopKey] = field(default_factory=deque)
    stats: TopicHopStats = field(default_factory=TopicHopStats)


class HopIntake:
    """Per topic: the keys of handled records (the newest ``window`` of them) and the writers' positions.

    The server calls :meth:`check` for each arriving record and :meth:`handled` once the record is on
    its way into the buffer (its key is committed in the same transaction as the record); a record
    that was dropped before that is not marked, so a replay of it is delivered.
    """

    def __init__(self, window: int, max_writers: int = MAX_WRITERS_PER_TOPIC) -> None:
        if window < 1:
            raise ValueError("the deduplication window must hold at least one key")
        self.window = window
        self._max_writers = max_writers
        self._clock = 0
        self._topics: dict[str, _TopicState] = {}
        # Per (topic, publisher): up to where a loss was counted since take_settled_marks last ran.
        self._settled_marks: dict[tuple[str, int], int] = {}
        # Per topic, (missing, gaps) of the earlier runs (the buffer's totals at the start) and of this
        # run handed over for the buffer's totals.
        self._before: dict[str, tuple[int, int]] = {}
        self._handed_over: dict[str, tuple[int, int]] = {}

    def load_loss_totals(self, totals: Mapping[str, tuple[int, int]]) -> None:
        """The buffer's lifetime totals of losses, per topic (missing, gaps), as this run starts."""
        self._before = dict(totals)

    def losses_not_handed_over(self) -> list[HopLosses]:
        """Per topic, what was counted (or taken back) since :meth:`losses_handed_over` last took it."""
        out = []
        for topic, state in self._topics.items():
            missing, gaps = self._handed_over.get(topic, (0, 0))
            if state.stats.missing != missing or state.stats.gaps != gaps:
                out.append(HopLosses(topic, state.stats.missing - missing, state.stats.gaps - gaps))
        return out

    def losses_handed_over(self, losses: Iterable[HopLosses]) -> None:
        """``losses`` are on their way into the buffer (submitted with records)."""
        for one in losses:
            missing, gaps = self._handed_over.get(one.topic, (0, 0))
            self._handed_over[one.topic] = (missing + one.missing, gaps + one.gaps)

    def _topic(self, topic: str) -> _TopicState:
        state = self._topics.get(topic)
        if state is None:
            state = self._topics[topic] = _TopicState(TopicWriters(self._max_writers))
        return state

    def load(self, keys: Iterable[HopKey]) -> None:
        """Take the keys kept in the buffer, oldest first: known duplicates and the writers' positions.

        Gaps among them were counted by the run that received them, so they are not counted again.
        """
        for key in keys:
            if key.topic.endswith(SOURCE_SUFFIX):
                state = self._topic(key.topic[: -len(SOURCE_SUFFIX)])
                writer_id = -key.source_ns
                state.source_max[writer_id] = max(key.seq, state.source_max.get(writer_id, 0))
                continue
            suffix = next((s for s in (ENDED_SUFFIX, SETTLED_SUFFIX) if key.topic.endswith(s)), "")
            if suffix:
                # Counted by the run that committed this: settled up to where the publisher ended, or
                # up to below the oldest record it still held.
                state = self._topic(key.topic[: -len(suffix)])
                ended = state.keyed.setdefault(-key.source_ns, _Keyed(key.seq + 1))
                if ended.settled <= key.seq:
                    ended.above = {s for s in ended.above if s > key.seq}
                    ended.settled = key.seq + 1
                continue
            state = self._topic(key.topic)
            if key not in state.seen:
                if key.source_ns < 0:
                    # What came before the oldest key kept is not known: nothing below it is counted.
                    writer = state.keyed.get(-key.source_ns)
                    if writer is None:
                        writer = state.keyed[-key.source_ns] = _Keyed(key.seq)
                    self._keyed_handled(writer, key.seq)
                else:
                    state.writers.observe(key.seq)
                self._remember(state, key)

    def check(self, topic: str, key: HopKey | None, low: int = 0, source: int = 0) -> Verdict:
        """What to do with an arriving record; ``low`` and ``source`` are from its hand-off key."""
        state = self._topic(topic)
        stats = state.stats
        stats.received += 1
        if key is None:
            stats.unkeyed += 1
            return _NOTHING_TO_SAY
        if key in state.seen:
            stats.duplicates += 1
            return _DUPLICATE
        if key.source_ns < 0:
            return self._check_keyed(topic, state, -key.source_ns, key.seq, low, source)
        skipped = state.writers.observe(key.seq)
        if skipped is None:
            stats.writers += 1
            return _NEW_WRITER
        if not skipped:
            return _NOTHING_TO_SAY
        stats.missing += skipped
        stats.gaps += 1
        return Verdict(skipped=skipped, first_skipped=key.seq - skipped)

    def _check_keyed(self, topic: str, state: _TopicState, writer_id: int, seq: int, low: int, source: int) -> Verdict:
        stats = state.stats
        self._clock += 1
        writer = state.keyed.get(writer_id)
        if writer is None:
            # A publisher first heard of now: what it holds from ``low`` on is sent again if need be.
            writer = self._new_keyed(state, writer_id, min(low, seq) if low > 0 else seq)
            stats.writers += 1
            self._keyed_handled(writer, seq)
            verdict = _NEW_WRITER
            forwarded = max((n for w, n in state.source_max.items() if w != writer_id), default=0)
            if seq == 1 and source > forwarded + 1 and forwarded:
                # The first record of a restarted publisher (measurement_server) forwards the source's
                # number ``source``; its predecessor forwarded up to ``forwarded``: what lies between
                # never reached destination_server (received by the dead one and not acknowledged,
                # or published while none ran).
                skipped = source - forwarded - 1
                stats.missing += skipped
                stats.gaps += 1
                verdict = Verdict(skipped=skipped, first_skipped=forwarded + 1, new_writer=True, source=True)
            if source:
                state.source_max[writer_id] = max(source, state.source_max.get(writer_id, 0))
            return verdict
        if source and source > state.source_max.get(writer_id, 0):
            state.source_max[writer_id] = source
        writer.used = self._clock
        verdict = _NOTHING_TO_SAY
        if seq < writer.settled and writer.counted:
            self._arrived_late(writer, seq, stats)
        if low > writer.settled:
            # The publisher holds nothing below low any more: what of it has not arrived is lost.
            handled = {s for s in writer.above if s < low}
            skipped = low - writer.settled - len(handled)
            first = writer.settled
            writer.above = {s for s in writer.above if s >= low}
            writer.settled = low
            if skipped > 0:
                stats.missing += skipped
                stats.gaps += 1
                verdict = Verdict(skipped=skipped, first_skipped=first)
                self._settled_marks[(topic, writer_id)] = low - 1
                counted = writer.counted
                if counted and counted[-1][1] + 1 >= first:
                    # A publisher dropping one record per record it publishes makes a gap per
                    # record: one range, or the late ones of older gaps would be counted anyway.
                    start, _, was_handled, arrived = counted[-1]
                    counted[-1] = (start, low - 1, was_handled | handled, arrived)
                else:
                    counted.append((first, low - 1, handled, set()))
                    del counted[:-COUNTED_RANGES]
        self._keyed_handled(writer, seq)
        return verdict

    def take_settled_marks(self) -> list[HopKey]:
        """The positions to commit with the records just checked: per publisher, the number up to which a
        loss was counted. Without them the next run, loading the keys, would find the lost numbers
        missing among them and count them again once the publisher's ``low`` passed them."""
        marks = [HopKey(topic + SETTLED_SUFFIX, -writer, seq) for (topic, writer), seq in self._settled_marks.items()]
        self._settled_marks.clear()
        return marks

    def _new_keyed(self, state: _TopicState, writer_id: int, settled: int) -> _Keyed:
        if len(state.keyed) >= self._max_writers:
            del state.keyed[min(state.keyed, key=lambda w: state.keyed[w].used)]
        writer = state.keyed[writer_id] = _Keyed(settled, used=self._clock)
        return writer

    @staticmethod
    def _arrived_late(writer: _Keyed, seq: int, stats: TopicHopStats) -> None:
        """A record counted as missing arrived after all (dropped by its publisher while on its way)."""
        for first, last, handled, arrived in writer.counted:
            if first <= seq <= last and seq not in handled and seq not in arrived:
                arrived.add(seq)
                stats.missing -= 1
                return

    @staticmethod
    def _keyed_handled(writer: _Keyed, seq: int) -> None:
        if seq < writer.settled:
            return
        writer.above.add(seq)
        while writer.settled in writer.above:
            writer.above.discard(writer.settled)
            writer.settled += 1

    def writer_ended(self, topic: str, writer_id: int, high: int, acked: int) -> tuple[int, int] | None:
        """A hand-off publisher ended (its process died) after publishing up to ``high``, acknowledged up to
        ``acked``: counts the numbers it published that never arrived as ``missing``.

        Returns ``(first, lost)``: the first number counted and how many (0: all arrived), or None when that
        was settled already (the same announcement again).
        A publisher this server does not know (its keys no longer in the buffer) is taken to have lost
        everything after ``acked``.
        """
        state = self._topic(topic)
        stats = state.stats
        self._clock += 1
        writer = state.keyed.get(writer_id)
        if writer is None:
            writer = self._new_keyed(state, writer_id, acked + 1)
        if writer.settled > high:
            return None
        first = max(writer.settled, acked + 1)
        handled = {s for s in writer.above if first <= s <= high}
        lost = max(0, high - first + 1 - len(handled))
        writer.above = {s for s in writer.above if s > high}
        writer.settled = high + 1
        writer.used = self._clock
        stats.writers_ended += 1
        if lost:
            stats.missing += lost
            stats.gaps += 1
            # A record of it still on its way (received after this) is taken off the count again.
            writer.counted.append((first, high, handled, set()))
            del writer.counted[:-COUNTED_RANGES]
        return first, lost

    def count_duplicate(self, topic: str) -> None:
        """Count a record received and dropped as a duplicate without :meth:`check` (a copy its caller saw)."""
        stats = self._topic(topic).stats
        stats.received += 1
        stats.duplicates += 1

    def handled(self, key: HopKey | None) -> None:
        """Remember ``key``: a later copy of the record is a duplicate."""
        if key is not None and not position_topic(key.topic):
            state = self._topic(key.topic)
            if key not in state.seen:
                self._remember(state, key)

    def _remember(self, state: _TopicState, key: HopKey) -> None:
        state.seen.add(key)
        state.order.append(key)
        while len(state.order) > self.window:
            state.seen.discard(state.order.popleft())

    def stats(self) -> dict[str, dict[str, int]]:
        """Per topic counters since the server started (the ``hop`` section of the metrics), and
        ``missing_lifetime`` / ``gaps_lifetime``: those of every run of this buffer, this one's included."""
        out: dict[str, dict[str, int]] = {}
        topics = dict(self._topics)  # read by the metrics' thread: a copy (one step under the GIL)
        for topic in sorted({*topics, *self._before}):
            state = topics.get(topic)
            counts = vars(state.stats if state is not None else TopicHopStats()).copy()
            missing, gaps = self._before.get(topic, (0, 0))
            counts["missing_lifetime"] = missing + counts["missing"]
            counts["gaps_lifetime"] = gaps + counts["gaps"]
            out[topic] = counts
        return out

    def totals(self) -> TopicHopStats:
        total = TopicHopStats()
        for state in self._topics.values():
            for name, value in vars(state.stats).items():
                setattr(total, name, getattr(total, name) + value)
        return total
