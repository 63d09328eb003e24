"""The acknowledged hand-off of records between DC's own servers (docs/delivery.md, "The hand-off").

measurement_server and group_server keep every record they publish to a topic that
destination_server reads until destination_server has committed it to its buffer; when a
destination_server (re)appears, or stops acknowledging a record for ``resend_after`` seconds while
it acknowledges others, the unacknowledged records are published again. A record is known by a
key its publisher writes into ``header.frame_id`` (:func:`frame_key`): the publisher's random id,
a number of its own (1, 2, 3, ...: a republished record keeps its number, where DDS would give
it a new one) and the oldest number the publisher still holds (``low``: everything below it was
acknowledged, or dropped at the memory limit, counted). destination_server deduplicates by that
key (dc_destinations.hop) and acknowledges cumulatively, one small message per group commit and
one a second: per topic and publisher the highest number up to which every record is committed.

The pure parts (:class:`Unacked`, :class:`AckTracker`, the key and the ack document) take no ROS;
:class:`HandoffSender` and :class:`AckPublisher` wire them to a node.
"""

from __future__ import annotations

import json
import secrets
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dc_core.handoff_marks import (
    ENDED_TOPIC,
    HIGH_AT,
    NUMBER,
    EndedWriters,
    WriterMark,
    ended_document,
    ended_qos,
)
from dc_core.params import param
from dc_core.private_files import make_folders
from dc_core.topics import resolve_topic

ACK_TOPIC = "dc/handoff_acks"
"""Relative: the acks of the destination_server of this namespace only (one DC per namespace)."""
RESEND_TOPIC = "dc/handoff_resent"
"""Records sent again go here, their topic after ``@`` in the key, for destination_server alone: on
the record topic every subscriber (a condition, group_server) would take old records for new ones."""
KEY_PREFIX = "dc:"
SOURCE_SUFFIX = " <- source"
"""Hop keys of this pseudo-topic keep, per publisher, the highest source number it forwarded."""
ENDED_SUFFIX = " <- ended"
"""Hop keys of this pseudo-topic keep, per publisher that ended, the number it ended at, once counted
(dc_core.handoff_marks)."""
SETTLED_SUFFIX = " <- settled"
"""Hop keys of this pseudo-topic keep, per publisher, the number up to which destination_server counted
what it dropped unacknowledged: the next run of destination_server does not count it again."""


def position_topic(topic: str) -> bool:
    """Whether a hop key of ``topic`` keeps a publisher's position rather than a record's key."""
    return topic.endswith((SOURCE_SUFFIX, ENDED_SUFFIX, SETTLED_SUFFIX))


ACK_PERIOD_S = 1.0
# Records republished per turn of the sender's timer: a restarted destination_server takes a
# backlog of minutes in slices, beside the live records, instead of all of it in one burst.
RESEND_SLICE = 500
# Slices are sent as acks come (after each of destination_server's commits): a timer at the pace of
# the slices cost measurement_server a wake-up of its executor 20 times a second. This one only
# logs the drops' summaries, and sends a slice when no ack came.
TICK_S = 1.0
# Records sent again and not yet acknowledged, at most: destination_server's queue on a record topic
# holds two histories (2,000), one of which a restart's replay can fill; more at once overflowed it
# (DDS overwrote records it had not taken, which were then sent a third time).
RESEND_WINDOW = 1000


@dataclass(frozen=True, kw_only=True)
class HandoffParams:
    unacked_limit_records: int = param(
        200_000,
        minimum=0,
        doc="Records kept until destination_server acknowledges them (0: none kept, the hand-off is off); "
        "beyond it the oldest are dropped, counted and logged",
    )
    unacked_limit_bytes: int = param(
        128 * 1024 * 1024, minimum=0, doc="The same limit in bytes of serialised records (0: no byte limit)"
    )
    resend_after: float = param(
        5.0, minimum=0.1, doc="Seconds after which a record not acknowledged while others are is published again"
    )


def new_writer_id() -> int:
    """A publisher's random id, positive and below 2**62 (its negative is kept as a hop key's source_ns)."""
    return secrets.randbits(62) or 1


def resent_topic(frame_id: str) -> str | None:
    """The topic a record received on :data:`RESEND_TOPIC` was published on; None without one."""
    if not frame_id.startswith(KEY_PREFIX) or "@" not in frame_id:
        return None
    return frame_id.split("@", 1)[1] or None


def frame_key(writer: int, seq: int, low: int, source: int = 0) -> str:
    key = f"{KEY_PREFIX}{writer:x}:{seq}:{low}"
    return f"{key}:{source}" if source > 0 else key


def parse_frame_key(frame_id: str) -> tuple[int, int, int, int] | None:
    """``(writer, seq, low, source)`` of a key written by :func:`frame_key` (source 0 when it has none).

    None for any other frame_id.
    """
    if not frame_id.startswith(KEY_PREFIX):
        return None
    parts = frame_id[len(KEY_PREFIX) :].split("@", 1)[0].split(":")
    if len(parts) not in (3, 4):
        return None
    try:
        writer, seq, low = int(parts[0], 16), int(parts[1]), int(parts[2])
        source = int(parts[3]) if len(parts) == 4 else 0
    except ValueError:
        return None
    if writer <= 0 or seq <= 0 or low <= 0 or low > seq or source < 0:
        return None
    return writer, seq, low, source


_forwarding = threading.local()


def forwarding(seq: int) -> None:
    """Records published from now on by this thread forward the record numbered ``seq`` by its own publisher (0: none).

    A StringStamped measurement passes its publisher's DDS sequence number on this way, so that
    destination_server, which keeps it with the records it commits, counts what a restart of the
    measurement_server in between lost (the records of your node it never forwarded). Set and
    cleared around the emit (a context manager cost ~3 us a record).
    """
    _forwarding.seq = seq


def forwarded_seq() -> int:
    """The sequence number :func:`forwarding` set on this thread (0: none)."""
    return int(getattr(_forwarding, "seq", 0))


# -- the publisher's side -------------------------------------------------------------------------


class Unacked:
    """The records of one publisher not acknowledged yet, oldest first, within a count and a byte limit.

    Not thread-safe: :class:`HandoffSender` holds a lock around it.
    """

    def __init__(self, limit_records: int, limit_bytes: int) -> None:
        self.limit_records = limit_records
        self.limit_bytes = limit_bytes
        self.writer = new_writer_id()
        self.next_seq = 1
        # (seq, serialised, first sent, monotonic s): tuples of plain values, which the garbage
        # collector stops tracking, so 200,000 held records cost it nothing (lists cost every
        # record published 3 us more once that many were held). Sent again: in ``_resent_at``.
        self._records: deque[tuple[int, bytes, float]] = deque()
        self._resent_at: dict[int, float] = {}
        self.bytes = 0
        self.dropped = 0  # dropped at the limit, never acknowledged
        self.acked = 0  # highest number acknowledged
        self.resent = 0

    def __len__(self) -> int:
        return len(self._records)

    @property
    def low(self) -> int:
        """The oldest number still held (the next one when none is)."""
        return self._records[0][0] if self._records else self.next_seq

    def take_number(self) -> tuple[int, int]:
        """``(seq, low)`` for the next record."""
        seq = self.next_seq
        self.next_seq += 1
        return seq, self._records[0][0] if self._records else seq

    def keep(self, seq: int, serialised: bytes, now: float) -> int:
        """Hold a published record; returns how many of the oldest were dropped to make room."""
        self._records.append((seq, serialised, now))
        self.bytes += len(serialised)
        return self.trim()

    @property
    def records(self) -> deque[tuple[int, bytes, float]]:
        return self._records

    def make_room(self, size: int) -> int:
        """Drop the oldest records until one more of ``size`` bytes fits; returns how many."""
        dropped = 0
        records = self._records
        while records and (
            len(records) >= self.limit_records or (self.limit_bytes and self.bytes + size > self.limit_bytes)
        ):
            self._forget()
            dropped += 1
        self.dropped += dropped
        return dropped

    def trim(self) -> int:
        """Drop the oldest records beyond the limits; returns how many."""
        dropped = 0
        while self._records and (
            len(self._records) > self.limit_records or (self.limit_bytes and self.bytes > self.limit_bytes)
        ):
            self._forget()
            dropped += 1
        self.dropped += dropped
        return dropped

    def ack(self, floor: int) -> int:
        """Forget the records up to ``floor``; returns how many."""
        if floor <= self.acked:
            return 0
        self.acked = floor
        released = 0
        while self._records and self._records[0][0] <= floor:
            self._forget()
            released += 1
        return released

    def _forget(self) -> None:
        seq, serialised, _ = self._records.popleft()
        self.bytes -= len(serialised)
        if self._resent_at:
            self._resent_at.pop(seq, None)

    def due(self, sent_before: float, now: float, limit: int) -> list[bytes]:
        """Up to ``limit`` records last sent before ``sent_before``, oldest first, marked as sent ``now``."""
        out: list[bytes] = []
        resent_at = self._resent_at
        for seq, serialised, sent in self._records:
            if resent_at.get(seq, sent) <= sent_before:
                resent_at[seq] = now
                out.append(serialised)
                if len(out) >= limit:
                    break
        self.resent += len(out)
        return out


@dataclass
class _Output:
    topic: str
    publisher: Any
    unacked: Unacked | None  # None: no destination_server reads the topic, nothing is kept
    resend_before: float = float("-inf")
    in_flight: int = 0  # sent again since the acknowledged number last moved
    progress_at: float = 0.0


class HandoffSender:
    """The records a server publishes to destination_server, kept until acknowledged and sent again.

    ``publish`` may be called from any thread; acks and resends run on the node's executor.
    """

    def __init__(
        self,
        node: Any,
        params: HandoffParams,
        acked_topics: Iterable[str],
        *,
        clock: Callable[[], float] = time.monotonic,
        marks: Path | None = None,
    ) -> None:
        """``marks``: the folder of this server's hand-off marks (:func:`dc_core.handoff_marks.marks_folder`);
        None: a kill of this server loses what it holds uncounted."""
        from dc_core.logs import BurstLog

        self._node = node
        self._params = params
        self._acked_topics = set(acked_topics) if params.unacked_limit_records > 0 else set()
        self._clock = clock
        self._lock = threading.Lock()
        self._outputs: dict[str, _Output] = {}
        self._destination: str | None = None
        self._subscription: Any = None
        self._resend_publisher: Any = None
        self._timer: Any = None
        self._last_ack = float("-inf")
        self._log = node.get_logger().get_child("handoff")
        self._drop_log = BurstLog(self._log.error, "records dropped before destination_server acknowledged them")
        # Where each publisher got to, on disk, and the publishers of earlier runs that ended holding
        # records (dc_core.handoff_marks); None where the folder cannot be used (logged once).
        self._marks_folder: Path | None = None
        if self._acked_topics and marks is not None:
            try:
                make_folders(marks)
                self._marks_folder = marks
            except OSError as exc:
                self._log.warning(
                    f"hand-off marks folder {marks} cannot be used ({exc}): records this server holds are lost "
                    "uncounted if it is killed"
                )
        self._marks: dict[str, WriterMark] = {}
        self._ended: EndedWriters | None = None
        self._ended_publisher: Any = None

    def output(self, topic: str, publisher: Any) -> Callable[[int, str, str], None]:
        """The publish function of one output topic: ``publish(stamp_ns, text, group_key)``."""
        from dc_core.stamped_cdr import write_string_stamped

        params = self._params
        unacked = (
            Unacked(params.unacked_limit_records, params.unacked_limit_bytes) if topic in self._acked_topics else None
        )
        self._outputs[topic] = _Output(topic, publisher, unacked)
        if unacked is None:

            def publish_only(stamp_ns: int, text: str, group_key: str) -> None:
                publisher.publish(write_string_stamped(stamp_ns, text, group_key))

            return publish_only
        lock = self._lock
        clock = self._clock
        drop_log = self._drop_log
        mark = self._mark(topic, unacked.writer)
        mark_map = mark.map if mark is not None else None
        pack_number = NUMBER.pack_into

        # The per-record path, inlined: each method call here cost ~0.1-0.3 us a record.
        records = unacked.records
        prefix = f"{KEY_PREFIX}{unacked.writer:x}:"
        limit_records = unacked.limit_records
        limit_bytes = unacked.limit_bytes or float("inf")

        def publish(stamp_ns: int, text: str, group_key: str) -> None:
            source = getattr(_forwarding, "seq", 0)
            with lock:
                seq = unacked.next_seq
                unacked.next_seq = seq + 1
                if mark_map is not None:
                    # Before the record leaves: a kill from here on is counted up to ``seq``.
                    pack_number(mark_map, HIGH_AT, seq)
                    if source and mark is not None and not mark.forwarding:
                        mark.forwards()
                # Room is made before the key is written: its low must not name a record dropped
                # right after (destination_server would wait for it, and acknowledge nothing more).
                dropped = unacked.make_room(0) if len(records) >= limit_records else 0
                low = records[0][0] if records else seq
                key = f"{prefix}{seq}:{low}:{source}" if source else f"{prefix}{seq}:{low}"
                serialised = write_string_stamped(stamp_ns, text, group_key, key)
                if unacked.bytes + len(serialised) > limit_bytes:
                    dropped += unacked.make_room(len(serialised))
                    if (records[0][0] if records else seq) != low:
                        low = records[0][0] if records else seq
                        key = f"{prefix}{seq}:{low}:{source}" if source else f"{prefix}{seq}:{low}"
                        serialised = write_string_stamped(stamp_ns, text, group_key, key)
                records.append((seq, serialised, clock()))
                unacked.bytes += len(serialised)
                publisher.publish(serialised)
            if dropped:
                drop_log.event(
                    dropped,
                    f"{topic}: unacked_limit_records {unacked.limit_records} / unacked_limit_bytes "
                    f"{unacked.limit_bytes} reached, oldest dropped",
                )

        return publish

    def _mark(self, topic: str, writer: int) -> WriterMark | None:
        if self._marks_folder is None:
            return None
        try:
            mark = self._marks[topic] = WriterMark(self._marks_folder, writer, topic)
        except OSError as exc:
            self._log.warning(f"{topic}: hand-off mark not written ({exc}): records held are lost uncounted if killed")
            return None
        return mark

    def start(self) -> None:
        """Listen to the acks, announce the publishers of earlier runs that ended holding records (at activation)."""
        from dc_interfaces.msg import StringStamped

        if not any(o.unacked is not None for o in self._outputs.values()) or self._timer is not None:
            return
        if self._ended is None and self._marks_folder is not None:
            self._ended = EndedWriters(self._marks_folder, self._log.warning)
            ended = self._ended.scan()
            if ended:
                self._ended_publisher = self._node.create_publisher(StringStamped, ENDED_TOPIC, ended_qos())
                self._log.warning(
                    f"{len(ended)} publisher(s) of an earlier run of this server ended holding records not "
                    "acknowledged (killed?): "
                    + ", ".join(f"{e.topic} up to {e.high - e.acked}" for e in ended)
                    + "; destination_server counts those it lacks"
                )
                self._announce()
        self._resend_publisher = self._node.create_publisher(StringStamped, RESEND_TOPIC, resend_qos())
        if self._subscription is None:
            self._subscription = self._node.create_subscription(StringStamped, ACK_TOPIC, self._on_ack, ack_qos())
        self._timer = self._node.create_timer(TICK_S, self._resend_slice)

    def stop(self) -> None:
        """Send nothing again (at deactivation); acks are still taken until :meth:`close`."""
        with self._lock:
            if self._resend_publisher is not None:
                self._node.destroy_publisher(self._resend_publisher)
                self._resend_publisher = None
        if self._timer is not None:
            self._node.destroy_timer(self._timer)
            self._timer = None
        self._drop_log.tick()

    def close(self) -> int:
        """Forget every output (at cleanup); returns and logs how many records were not acknowledged."""
        self.stop()
        if self._subscription is not None:
            self._node.destroy_subscription(self._subscription)
            self._subscription = None
        with self._lock:
            held = {o.topic: len(o.unacked) for o in self._outputs.values() if o.unacked is not None and o.unacked}
            self._outputs.clear()
            # Kept where records are held: the next start announces how far this publisher got.
            for topic, mark in self._marks.items():
                mark.close(keep=topic in held)
            self._marks.clear()
        if self._ended is not None:
            self._ended.release()
            self._ended = None
        if self._ended_publisher is not None:
            self._node.destroy_publisher(self._ended_publisher)
            self._ended_publisher = None
        if held:
            # At a stop, destination_server usually has them (it commits what it received when it
            # stops, after this server), but its last acks come too late to be seen: a warning.
            self._log.warning(
                "records not acknowledged by destination_server when this server stopped: "
                + ", ".join(f"{topic} {count}" for topic, count in sorted(held.items()))
                + "; delivered if destination_server received them before it stopped, lost otherwise (counted by "
                "destination_server after this server's next start)"
            )
        return sum(held.values())

    def _on_ack(self, msg: Any) -> None:
        document = parse_ack(msg.data)
        if document is None:
            return
        now = self._clock()
        self._last_ack = now
        hello = document["instance"] != self._destination
        self._destination = document["instance"]
        acks = document["acks"]
        with self._lock:
            for output in self._outputs.values():
                unacked = output.unacked
                if unacked is None:
                    continue
                floor = acks.get((output.topic, unacked.writer))
                moved = floor is not None and unacked.ack(floor)
                if moved and output.topic in self._marks:
                    self._marks[output.topic].acked(unacked.acked)
                if moved or hello:
                    output.in_flight = 0
                    output.progress_at = now
                elif now - output.progress_at > self._params.resend_after:
                    output.in_flight = 0  # what was sent again got lost too: the window opens again
                    output.progress_at = now
                # A new destination_server has none of what is held; a known one is sent again
                # what it has not acknowledged for resend_after seconds.
                cutoff = now if hello else now - self._params.resend_after
                output.resend_before = max(output.resend_before, cutoff)
        if hello:
            self._log.info(f"destination_server {document['instance']} acknowledges: sending what it lacks")
        if self._ended is not None and self._ended.retire(acks):
            self._announce()
        self._resend_slice()

    def _announce(self) -> None:
        """The ended publishers not retired yet (an empty list replaces the last one in the history)."""
        from dc_interfaces.msg import StringStamped

        if self._ended is None or self._ended_publisher is None:
            return
        msg = StringStamped()
        msg.data = ended_document(self._node.get_name(), self._ended.ended())
        self._ended_publisher.publish(msg)

    def _resend_slice(self) -> None:
        self._drop_log.tick()
        now = self._clock()
        with self._lock:
            resend = self._resend_publisher
            if resend is None:
                return
            for output in self._outputs.values():
                room = min(RESEND_SLICE, RESEND_WINDOW - output.in_flight)
                if output.unacked is None or output.resend_before == float("-inf") or room <= 0:
                    continue
                due = output.unacked.due(output.resend_before, now, room)
                output.in_flight += len(due)
                for serialised in due:
                    resend.publish(_addressed(serialised, output.topic))

    def metrics(self) -> dict[str, dict[str, int]]:
        """Per topic: records held, their bytes, dropped at the limit, sent again (the ``handoff`` section)."""
        with self._lock:
            return {
                o.topic: {
                    "unacked": len(o.unacked),
                    "unacked_bytes": o.unacked.bytes,
                    "dropped": o.unacked.dropped,
                    "resent": o.unacked.resent,
                }
                for o in self._outputs.values()
                if o.unacked is not None
            }


def _addressed(serialised: bytes, topic: str) -> bytes:
    """The record with its topic after ``@`` in its key, for :data:`RESEND_TOPIC`."""
    from dc_core.stamped_cdr import read_keyed_string_stamped, read_stamped_record, write_string_stamped

    stamp_ns, data, frame_id = read_keyed_string_stamped(serialised)
    return write_string_stamped(stamp_ns, data, read_stamped_record(serialised)[2], f"{frame_id}@{topic}")


def resend_qos() -> Any:
    """Deep enough for a whole window of records sent again."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=2 * RESEND_WINDOW,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
    )


def ack_qos() -> Any:
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=10,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
    )


def destination_inputs(servers: Mapping[str, Any], namespace: str = "/") -> set[str]:
    """The topics the destination_server section of a parameter file reads (no plugin imported),
    fully qualified in ``namespace`` as the destination server there resolves them."""
    section = servers.get("destination_server")
    if not isinstance(section, dict):
        return set()
    params = section.get("ros__parameters", section)
    topics: set[str] = set()
    names = params.get("destination_plugins") if isinstance(params, dict) else None
    for name in names if isinstance(names, list) else []:
        plugin = params.get(name) if isinstance(name, str) else None
        inputs = plugin.get("inputs") if isinstance(plugin, dict) else None
        topics.update(
            resolve_topic(i, namespace, "destination_server")
            for i in (inputs if isinstance(inputs, list) else [])
            if isinstance(i, str) and i
        )
    return topics


# -- destination_server's side --------------------------------------------------------------------


def ack_document(instance: str, acks: Iterable[tuple[str, int, int]]) -> str:
    return json.dumps({"instance": instance, "acks": [[topic, f"{w:x}", floor] for topic, w, floor in acks]})


def parse_ack(text: str) -> dict[str, Any] | None:
    """``{"instance": str, "acks": {(topic, writer): floor}}``; None for anything else."""
    try:
        document = json.loads(text)
        acks = {(str(topic), int(writer, 16)): int(floor) for topic, writer, floor in document["acks"]}
        return {"instance": str(document["instance"]), "acks": acks}
    except (ValueError, TypeError, KeyError):
        return None


@dataclass
class _AckWriter:
    low: int = 0  # the publisher's oldest record held, from its newest record's key
    floor: int = 0  # every record up to here is committed (or below low)
    committed: set[int] | None = None
    used: float = 0.0


MAX_ACK_WRITERS = 64


class AckTracker:
    """Per topic and publisher, the highest number up to which every record is committed.

    ``saw`` is called by the intake (the publisher's ``low``), ``committed`` by the writer thread
    after a group commit, with the hop keys it committed; both under one lock.
    """

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._lock = threading.Lock()
        self._writers: dict[tuple[str, int], _AckWriter] = {}
        self._clock = clock

    def _writer(self, topic: str, writer: int) -> _AckWriter:
        state = self._writers.get((topic, writer))
        if state is None:
            if len(self._writers) >= MAX_ACK_WRITERS:
                del self._writers[min(self._writers, key=lambda k: self._writers[k].used)]
            state = self._writers[(topic, writer)] = _AckWriter(committed=set())
        state.used = self._clock()
        return state

    def saw(self, topic: str, writer: int, low: int) -> None:
        with self._lock:
            state = self._writer(topic, writer)
            if low > state.low:
                state.low = low

    def committed(self, keys: Iterable[tuple[str, int, int]]) -> bool:
        """Take the hop keys of a commit; True when a floor moved (an ack is worth sending)."""
        moved = False
        with self._lock:
            touched: set[tuple[str, int]] = set()
            for topic, source_ns, seq in keys:
                if source_ns < 0 and topic.endswith(ENDED_SUFFIX):
                    # A publisher that ended at ``seq``, its losses counted: acknowledged to its end, so
                    # that its successor forgets it (dc_core.handoff_marks).
                    state = self._writer(topic[: -len(ENDED_SUFFIX)], -source_ns)
                    state.low = max(state.low, seq + 1)
                    touched.add((topic[: -len(ENDED_SUFFIX)], -source_ns))
                elif source_ns < 0 and not position_topic(topic):
                    state = self._writer(topic, -source_ns)
                    assert state.committed is not None
                    if seq > state.floor:
                        state.committed.add(seq)
                        touched.add((topic, -source_ns))
            for key in touched:
                moved = self._advance(self._writers[key]) or moved
            # A publisher's low may have moved with no commit of its own (its acks came from before).
            for state in self._writers.values():
                if state.low - 1 > state.floor:
                    moved = self._advance(state) or moved
        return moved

    @staticmethod
    def _advance(state: _AckWriter) -> bool:
        if state.low == 0:
            return False  # where the publisher's records start is not known yet
        committed = state.committed
        assert committed is not None
        floor = max(state.floor, state.low - 1)
        while floor + 1 in committed:
            floor += 1
        if floor == state.floor:
            return False
        state.floor = floor
        state.committed = {s for s in committed if s > floor}
        return True

    def acks(self) -> list[tuple[str, int, int]]:
        with self._lock:
            for state in self._writers.values():
                self._advance(state)  # a low learnt from records that were all duplicates
            return [(topic, writer, s.floor) for (topic, writer), s in self._writers.items() if s.low]


class AckPublisher:
    """destination_server's acks: one message after each group commit that moved a floor, and one a second."""

    def __init__(self, node: Any) -> None:
        from dc_interfaces.msg import StringStamped

        self.tracker = AckTracker()
        self.instance = secrets.token_hex(8)
        self._msg_type = StringStamped
        self._publisher = node.create_publisher(StringStamped, ACK_TOPIC, ack_qos())
        self._node = node
        self._lock = threading.Lock()
        self.sent = 0

    def on_commit(self, keys: Iterable[tuple[str, int, int]]) -> None:
        """The writer thread's callback after a group commit succeeded."""
        if self.tracker.committed(keys):
            self.send()

    def send(self) -> None:
        msg = self._msg_type()
        msg.data = ack_document(self.instance, self.tracker.acks())
        with self._lock:
            self._publisher.publish(msg)
            self.sent += 1

    def destroy(self) -> None:
        with self._lock:
            self._node.destroy_publisher(self._publisher)
            self._publisher = _Closed()


class _Closed:
    def publish(self, msg: Any) -> None:
        return None
