"""Recorder measurement: the raw messages of chosen topics from before and after a trigger, as one MCAP file.

Every message of ``topics`` is kept in memory as the subscription took it — serialised, never decoded
(dc_measurements.recorder.ring) — for ``pre_trigger`` seconds, within ``max_memory_mb``. A trigger — the
measurement's conditions becoming true, a call of the ``dc/recorder/<name>/trigger`` service, a
``std_msgs/String`` reason on the topic of the same name — opens a window from ``pre_trigger`` before it
to ``post_trigger`` after it; a trigger inside it extends it (dc_measurements.recorder.window). Once the
window has closed, the worker writes its messages as an MCAP file (dc_measurements.recorder.mcap_file)
and the record of the incident is published: paths, times, reasons, per-topic counts, what the memory
bound cut. A topic's type is given (``types``) or learnt from the ROS graph: the topic is subscribed as soon
as its type is known, before it has a publisher, so that a topic appearing after the recorder started loses
none of its first messages to the graph check (once a second); the publishers' QoS is matched once they show.
What the middleware drops before the recorder takes it (a full subscription queue, a best-effort sample lost)
is counted from the gaps in the publisher's sequence numbers (``lost_in_transport``).
"""

from __future__ import annotations

import functools
import importlib
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from dc_core.errors import ConfigError, PluginError
from dc_core.logs import BurstLog
from dc_core.measurement import Measurement, MeasurementContext
from dc_core.params import param
from dc_core.topics import ros_topic, topic_problem
from dc_core.worker import Outcome
from dc_measurements.recorder.definitions import Definitions
from dc_measurements.recorder.mcap_file import COMPRESSIONS, Channel, Written, write_mcap
from dc_measurements.recorder.ring import LATCHED_KEEP, NEVER, Entry, Ring, Writing
from dc_measurements.recorder.window import Incident, Windows
from dc_measurements.recorder.window import Outcome as TriggerOutcome
from dc_measurements.saved_files import ReservedPaths, file_locations

_SUFFIX = ".mcap"
# A subscription's queue between two drains of the server's loop: enough for a 1 kHz topic.
DEPTH = 100
# How often the graph is asked for topics not seen yet (costs a graph walk: not every poll).
DISCOVERY_PERIOD_S = 1.0
# Without conditions, the recorder's own poll period while a window is open or being written (it has no
# timer otherwise: an idle recorder costs only its messages).
OWN_POLL_S = 0.1
MB = 1024 * 1024
# A window is written this long after its end: a message received just before the end may still wait in its
# subscription's queue for the server's loop to take it (its receive time is the middleware's).
CLOSE_GRACE_NS = 250_000_000
# A file that cannot be written (a full disk, a folder that cannot be made) is tried again this much later,
# its window's messages kept in memory meanwhile, WRITE_TRIES times in all; then the window is dropped, counted.
WRITE_RETRY_NS = 5_000_000_000
WRITE_TRIES = 3
# After the early subscription of a topic is gone, its messages are still compared with those kept for this
# many graph checks: the new subscription may hold, queued, some the early one gave.
HANDOVER_CHECKS = 2
# A topic whose sequence numbers come from several publishers is not checked for gaps: the numbers of two
# publishers interleave, and rclpy's message info does not say whose a message is. The graph is asked again
# at the next break in the numbers this much later (a graph query per message would cost more than the ring).
SEVERAL_RECHECK_S = 1.0
# A gap is kept this long past what a window may still need (pre_trigger, an open window), so that the record
# of a window written late (the close grace, write retries) still finds its gaps.
GAPS_MARGIN_NS = 60_000_000_000


def _types_problem(types: list[str]) -> str | None:
    bad = [t for t in types if t and len(t.split("/")) != 3]
    return f"message types as package/msg/Name, or empty to learn it from the graph (not: {bad})" if bad else None


def _topics_problem(topics: list[str]) -> str | None:
    if not topics:
        return "at least one topic"
    bad = [t for t in topics if topic_problem(t)]
    if bad:
        return f"ROS 2 topic names (not: {bad})"
    if len(set(topics)) != len(topics):
        return "each topic once"
    return None


@dataclass(frozen=True, kw_only=True)
class RecorderParams:
    topics: list[str] = param(
        doc="Topics recorded, any message type (taken serialised, never decoded)", check=_topics_problem
    )
    pre_trigger: float = param(10.0, minimum=0.0, doc="Seconds recorded before a trigger")
    post_trigger: float = param(5.0, minimum=0.0, doc="Seconds recorded after the last trigger of a window")
    max_memory_mb: float = param(
        256.0,
        minimum=0.001,
        doc="Bound of the messages kept in memory (MiB): past it the oldest go first, counted (lost_to_bound)",
    )
    cooldown: float = param(
        0.0, minimum=0.0, doc="Seconds after a window closed during which triggers are counted, not recorded"
    )
    max_incidents_per_hour: int = param(
        60, minimum=1, doc="Incidents recorded in any hour; further triggers are counted"
    )
    save_path: str = param(
        "incidents/%Y-%m-%dT%H:%M:%S",
        doc="Path of the MCAP file without .mcap, under save_local_base_path/all_base_path ($ENV, strftime of the "
        "window's start)",
    )
    types: list[str] = param(
        [],
        doc="Message type of each topic (same order as topics; empty: learnt from the graph): subscribed at "
        "configure, before the topic has a publisher",
        check=_types_problem,
    )
    compression: str = param("zstd", choices=COMPRESSIONS, doc="Compression of the MCAP file's chunks")
    trigger_service: bool = param(
        True, doc="Offer the dc/recorder/<name>/trigger service (std_srvs/Trigger) and topic (std_msgs/String)"
    )

    def __post_init__(self) -> None:
        if self.types and len(self.types) != len(self.topics):
            raise ConfigError("types", f"one entry per topic ({len(self.topics)}), not {len(self.types)}")


@dataclass
class _Closing:
    """A window whose end has passed, written at ``write_at_ns`` (CLOSE_GRACE_NS later)."""

    incident: Incident
    entries: list[Entry]
    cut: bool
    lost: list[int]
    write_at_ns: int
    # The window's messages in memory for the worker, in the ring's bound (Ring.writing).
    held: Writing
    failures: int = 0


@dataclass
class _Topic:
    name: str  # resolved
    typename: str = ""
    subscription: Any = None
    channel: Channel | None = None
    latched: bool = False
    message_class: Any = None
    # Subscribed before any publisher showed (EARLY_QOS): the publishers' QoS is matched once they do.
    early: bool = False
    # The early subscription, kept until the one of the publishers' QoS takes its first message: both take
    # the messages meanwhile (each kept once); then what the early one still holds is taken before it goes.
    retiring: Any = None
    # Graph checks left, once the early subscription went, before the topic's messages are no longer
    # compared with those already kept (HANDOVER_CHECKS).
    handover: int = 0


# A subscription made before any publisher shows: best effort and volatile match every publisher (a
# reliable one that met a reliable subscription would make the publisher of a best-effort topic, a
# sensor-data camera's driver, warn about incompatible QoS). Once the publishers show, a reliable or a
# latching one gets a subscription of its QoS (reliability, the latched messages sent before).
EARLY_QOS = QoSProfile(depth=DEPTH, reliability=ReliabilityPolicy.BEST_EFFORT, durability=DurabilityPolicy.VOLATILE)


def _message_class(typename: str) -> Any:
    package, kind, name = typename.split("/")
    return getattr(importlib.import_module(f"{package}.{kind}"), name)


def _qos_of_publishers(node: Any, topic: str) -> tuple[QoSProfile, bool, str]:
    """A subscription every publisher of ``topic`` matches, whether they latch, and their QoS as rosbag2 writes it."""
    infos = node.get_publishers_info_by_topic(topic)
    best_effort = any(i.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT for i in infos)
    latched = bool(infos) and all(i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for i in infos)
    qos = QoSProfile(
        depth=LATCHED_KEEP if latched else DEPTH,
        reliability=ReliabilityPolicy.BEST_EFFORT if best_effort else ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
    )
    return qos, latched, "".join(_offered_qos(i.qos_profile) for i in infos)


def _offered_qos(qos: Any) -> str:
    """One publisher's QoS as rosbag2 writes it in ``offered_qos_profiles`` (rosbags reads every key)."""

    def duration(value: Any) -> str:
        sec, nsec = divmod(int(value.nanoseconds), 1_000_000_000)
        return f"{{sec: {sec}, nsec: {nsec}}}"

    return (
        f"- history: {qos.history.name.lower()}\n  depth: {qos.depth}\n"
        f"  reliability: {qos.reliability.name.lower()}\n  durability: {qos.durability.name.lower()}\n"
        f"  deadline: {duration(qos.deadline)}\n  lifespan: {duration(qos.lifespan)}\n"
        f"  liveliness: {qos.liveliness.name.lower()}\n"
        f"  liveliness_lease_duration: {duration(qos.liveliness_lease_duration)}\n"
        f"  avoid_ros_namespace_conventions: {str(qos.avoid_ros_namespace_conventions).lower()}\n"
    )


class Recorder(Measurement[RecorderParams]):
    """Incident recorder: raw messages from before and after a trigger, as an MCAP file, one record per incident."""

    conditions_trigger = True

    def __init__(self, context: MeasurementContext, params: RecorderParams) -> None:
        super().__init__(context, params)
        p = params
        self._topics = [_Topic(t) for t in p.topics]
        self._ring = Ring(int(p.max_memory_mb * MB), int(p.pre_trigger * 1e9), len(p.topics))
        self._windows = Windows(
            int(p.pre_trigger * 1e9), int(p.post_trigger * 1e9), int(p.cooldown * 1e9), p.max_incidents_per_hour
        )
        self._received = [0] * len(p.topics)
        # Per topic: the last publication sequence number taken (0: none yet), the messages its publisher sent
        # that never came (gaps), and until when (monotonic) it counts as having several publishers.
        self._last_seq = [0] * len(p.topics)
        self._lost_in_transport = [0] * len(p.topics)
        self._several_until = [0.0] * len(p.topics)
        # (receive ns, topic index, messages lost or None: not checked from then on for SEVERAL_RECHECK_S)
        self._gaps: deque[tuple[int, int, int | None]] = deque()
        self._definitions = Definitions()
        self._without_definition_warned: set[str] = set()
        self._closing: deque[_Closing] = deque()
        # Windows whose file could not be written (a full disk): kept, tried again WRITE_RETRY_NS later.
        self._retrying: deque[_Closing] = deque()
        self._reserved = ReservedPaths()
        self._conditions_met = False
        self._next_discovery = 0.0
        self._absent_warned = False
        self._bound_warned = False
        self._services: list[Any] = []
        self._poll_timer: Any = None
        # Per topic index, while two subscriptions take it: (publisher's stamp, size) of what was kept.
        self._overlap: dict[int, set[tuple[int, int]]] = {}
        self._discovery_timer: Any = None
        self._save_log = BurstLog(context.logger.error, f"measurement {context.name}: incidents not saved")
        self.incidents = 0
        self.write_errors = 0
        self.writing = 0
        self.unpublished = 0
        self.incidents_dropped = 0

    # -- lifecycle -------------------------------------------------------------------------------
    @property
    def timer_driven(self) -> bool:
        # Only conditions need judging at every poll; the other triggers are callbacks, and the windows
        # they open are polled by the recorder's own timer while they need it (see _set_timers).
        return self.has_trigger_conditions

    def on_activate(self) -> None:
        if self.timer_driven:
            return
        self._poll_timer = self.context.create_timer(OWN_POLL_S, lambda: self.on_poll(None))
        self._discovery_timer = self.context.create_timer(DISCOVERY_PERIOD_S, self._discover)
        self._set_timers()

    def _set_timers(self) -> None:
        """Without conditions: each own timer runs only while it has work (a cancelled timer never wakes)."""
        if self._poll_timer is None:
            return
        busy = self._windows.open is not None or bool(self._closing) or bool(self._retrying) or self.writing > 0
        for timer, needed in (
            (self._poll_timer, busy),
            (self._discovery_timer, any(self._pending(t) for t in self._topics)),
        ):
            if needed and timer.is_canceled():
                timer.reset()
            elif not needed and not timer.is_canceled():
                timer.cancel()

    def on_configure(self) -> None:
        p = self.params
        try:
            import mcap.writer  # noqa: F401
        except ImportError as exc:
            raise PluginError(
                f"{self.context.name}: the Recorder needs the mcap package ({exc}): pip install 'ros2-dc[recorder]'"
            ) from None
        node = self.context.node
        if node is None:
            raise PluginError(f"{self.context.name}: the Recorder needs the server's ROS node")
        for topic in self._topics:
            topic.name = node.resolve_topic_name(ros_topic(topic.name))
        if p.trigger_service:
            from std_msgs.msg import String
            from std_srvs.srv import Trigger

            name = f"dc/recorder/{self.context.name}/trigger"
            self._services = [
                node.create_service(Trigger, name, self._on_trigger_service),
                node.create_subscription(String, name, self._on_trigger_message, 10),
            ]
        self._discover()

    def on_cleanup(self) -> None:
        node = self.context.node
        for topic in self._topics:
            for subscription in (topic.subscription, topic.retiring):
                if subscription is not None:
                    self.context.unsubscribe(subscription)
            topic.subscription = topic.retiring = None
        for entity in self._services:
            if hasattr(entity, "service_name"):
                node.destroy_service(entity)
            else:
                node.destroy_subscription(entity)
        self._services = []
        self._ring.clear()

    def on_deactivate(self) -> None:
        for timer in (self._poll_timer, self._discovery_timer):
            if timer is not None:
                self.context.destroy_timer(timer)
        self._poll_timer = self._discovery_timer = None
        # An open window closes now; it and those waiting for their last messages are written here (the
        # records' publisher is already inactive): not lost with the ring, their records said in the log.
        incident = self._windows.open
        if incident is not None:
            incident.end_ns = min(incident.end_ns, time.time_ns())
            self._windows.due(incident.end_ns)
            self._closing.append(self._snapshot(incident, 0))
        self._closing.extend(self._retrying)
        self._retrying.clear()
        while self._closing:
            closing = self._closing.popleft()
            job, sample, base = self._prepare(closing)
            try:
                self._note_written(sample, job())
            except Exception as exc:
                self.write_errors += 1
                self.incidents_dropped += 1
                self.context.logger.error(
                    f"measurement {self.context.name}: incident not saved at deactivate, dropped: {exc}: {sample}"
                )
                continue
            finally:
                self._reserved.release(base)
                self._ring.written(closing.held)
            self.unpublished += 1
            self.context.logger.warning(
                f"measurement {self.context.name}: incident saved at deactivate as {sample['local_paths']['mcap']}, "
                f"its window closed early; its record is not published: {sample}"
            )

    # -- intake ----------------------------------------------------------------------------------
    @staticmethod
    def _pending(topic: _Topic) -> bool:
        return topic.subscription is None or topic.early or topic.retiring is not None or topic.handover > 0

    def _discover(self) -> None:
        pending = [t for t in self._topics if self._pending(t)]
        if not pending:
            return
        node = self.context.node
        types: dict[str, list[str]] = {}
        if any(not t.typename for t in pending):
            types = dict(node.get_topic_names_and_types())
        for topic in pending:
            if topic.handover > 0:
                topic.handover -= 1
                if not topic.handover:
                    self._overlap.pop(self._topics.index(topic), None)
            if topic.subscription is not None:
                if topic.early and node.count_publishers(topic.name):
                    self._settle(topic)
                continue
            if topic.typename:
                continue  # a type that is not installed here, said once
            index = self._topics.index(topic)
            declared = self.params.types[index] if self.params.types else ""
            typenames = types.get(topic.name)
            typename = declared or (typenames[0] if typenames else "")
            if not typename:
                continue
            topic.typename = typename
            try:
                message_class = _message_class(typename)
            except (ImportError, AttributeError, ValueError) as exc:
                self.context.logger.warning(
                    f"measurement {self.context.name}: {topic.name} ({typename}) not recorded: "
                    f"its type is not installed here ({exc})"
                )
                continue
            topic.message_class = message_class
            if node.count_publishers(topic.name):
                self._subscribe(topic, *_qos_of_publishers(node, topic.name))
            else:
                # (a topic this very server subscribes to, for a condition, is in the graph before anyone
                # publishes it: its type is known, the QoS not yet)
                topic.early = True
                self._subscribe(topic, EARLY_QOS, False, "")
        self._set_timers()

    def _subscribe(self, topic: _Topic, qos: QoSProfile, latched: bool, offered: str) -> None:
        topic.latched = latched
        topic.channel = Channel(topic.name, topic.typename, offered)
        index = self._topics.index(topic)
        # A topic subscribed early may be taken by two subscriptions for a while (see _settle).
        handler = self._on_message
        if topic.retiring is not None:
            handler = self._on_new_subscription
        elif topic.early:
            handler = self._on_message_once
        callback = functools.partial(handler, index, latched)
        topic.subscription = self.context.subscribe(topic.message_class, topic.name, callback, qos, raw=True)

    def _settle(self, topic: _Topic) -> None:
        """A topic subscribed early now has publishers: their QoS goes in the file, and reliable or latching
        ones get a subscription of their QoS, the early one kept until that one takes its first message."""
        qos, latched, offered = _qos_of_publishers(self.context.node, topic.name)
        topic.early = False
        if qos.reliability == EARLY_QOS.reliability and not latched:
            topic.channel = Channel(topic.name, topic.typename, offered)
            return
        # Until the early subscription goes, a message both take is kept once: by its publisher's
        # stamp and size (a latching publisher also resends what the early one took already).
        index = self._topics.index(topic)
        self._overlap[index] = {(e[1], len(e[3])) for e in self._ring.between(0, NEVER) if e[2] == index}
        topic.retiring = topic.subscription
        self._subscribe(topic, qos, latched, offered)

    def _on_new_subscription(self, index: int, latched: bool, data: bytes, info: Any) -> None:
        """A message of the subscription of the publishers' QoS. At its first, the publishers reach it (matched
        and sending: an event, not a delay): what the early subscription still holds is taken — all sent
        before this one or also taken here, kept once — and the early one goes. A message neither got is a gap
        in the publisher's sequence numbers, counted."""
        topic = self._topics[index]
        retiring = topic.retiring
        if retiring is not None:
            topic.retiring = None
            topic.handover = HANDOVER_CHECKS
            self.context.unsubscribe(retiring, take_queued=True)
            self._set_timers()
        self._on_message_once(index, latched, data, info)

    def _on_message(self, index: int, latched: bool, data: bytes, info: Any) -> None:
        self._received[index] += 1
        seq = info["publication_sequence_number"]
        if seq == self._last_seq[index] + 1:
            self._last_seq[index] = seq
        else:
            self._sequence_break(index, seq, info["received_timestamp"])
        self._ring.append(info["received_timestamp"], info["source_timestamp"], index, data, latched)

    def _sequence_break(self, index: int, seq: int | None, receive_ns: int) -> None:
        """A message that does not follow the last one of its topic: a gap (counted), a topic's first message,
        a publisher restarted, several publishers (not checked), or a message a gap was counted for that the
        other subscription of a handover had after all (the count taken back)."""
        last = self._last_seq[index]
        self._last_seq[index] = seq or 0
        if (seq and not last) or time.monotonic() < self._several_until[index]:
            return  # its first message, or said unchecked less than SEVERAL_RECHECK_S ago
        if not seq:  # this middleware gives no sequence numbers (0: unsupported)
            self._not_checked(index, receive_ns)
            return
        if self.context.node.count_publishers(self._topics[index].name) > 1:
            self._not_checked(index, receive_ns)
            return
        if seq > last:
            self._gap(receive_ns, index, seq - last - 1)
        elif index in self._overlap and self._lost_in_transport[index] > 0:
            self._last_seq[index] = last
            self._gap(receive_ns, index, -1)

    def _not_checked(self, index: int, receive_ns: int) -> None:
        self._several_until[index] = time.monotonic() + SEVERAL_RECHECK_S
        self._note_gap(receive_ns, index, None)

    def _gap(self, receive_ns: int, index: int, lost: int) -> None:
        self._lost_in_transport[index] += lost
        self._note_gap(receive_ns, index, lost)

    def _note_gap(self, receive_ns: int, index: int, lost: int | None) -> None:
        gaps = self._gaps
        gaps.append((receive_ns, index, lost))
        horizon = min(receive_ns - self._ring.keep_ns, self._ring.hold_from_ns) - GAPS_MARGIN_NS
        while gaps[0][0] < horizon:
            gaps.popleft()

    def _transport_losses(self, start_ns: int, end_ns: int) -> tuple[list[int], list[bool]]:
        """Per topic, the messages lost in transport in [start_ns, end_ns], and whether some of it went unchecked."""
        lost = [0] * len(self._topics)
        unchecked = [False] * len(self._topics)
        recheck_ns = int(SEVERAL_RECHECK_S * 1e9)
        for receive_ns, index, count in self._gaps:
            if count is None:
                unchecked[index] = unchecked[index] or start_ns - recheck_ns <= receive_ns <= end_ns
            elif start_ns <= receive_ns <= end_ns:
                lost[index] += count
        return [max(0, n) for n in lost], unchecked

    def _on_message_once(self, index: int, latched: bool, data: bytes, info: Any) -> None:
        seen = self._overlap.get(index)
        if seen is not None:
            key = (info["source_timestamp"], len(data))
            if key in seen:
                return
            seen.add(key)
        self._on_message(index, latched, data, info)

    # -- triggers --------------------------------------------------------------------------------
    def _on_trigger_service(self, request: Any, response: Any) -> Any:
        outcome = self.trigger("service")
        response.success = outcome in (TriggerOutcome.OPENED, TriggerOutcome.EXTENDED)
        response.message = outcome.value
        return response

    def _on_trigger_message(self, message: Any) -> None:
        self.trigger(message.data or "topic")

    def trigger(self, reason: str, now_ns: int | None = None) -> TriggerOutcome:
        now_ns = time.time_ns() if now_ns is None else now_ns
        outcome = self._windows.trigger(now_ns, reason)
        if outcome is TriggerOutcome.OPENED:
            assert self._windows.open is not None
            start = self._windows.open.start_ns
            # Messages of the window the bound let go before the trigger count as its losses too.
            self._ring.take_lost_in_window()
            self._ring.lost_in_window = self._ring.lost_since(start)
            self._ring.hold_from_ns = start
            self._set_timers()
        self.context.logger.info(f"measurement {self.context.name}: trigger ({reason}): {outcome.value}")
        return outcome

    def on_poll(self, conditions_met: bool | None) -> None:
        now_ns = time.time_ns()
        self._save_log.tick()
        met = bool(conditions_met)
        if met and not self._conditions_met:
            self.trigger("conditions", now_ns)
        self._conditions_met = met
        self._check_bound(now_ns)
        if time.monotonic() >= self._next_discovery:
            self._next_discovery = time.monotonic() + DISCOVERY_PERIOD_S
            self._discover()
        incident = self._windows.due(now_ns)
        if incident is not None:
            self._closing.append(self._snapshot(incident, now_ns + CLOSE_GRACE_NS))
        while self._closing and self._closing[0].write_at_ns <= now_ns:
            self._close(self._closing.popleft())
        while self._retrying and self._retrying[0].write_at_ns <= now_ns:
            self._close(self._retrying.popleft())
        self._set_timers()

    def _check_bound(self, now_ns: int) -> None:
        """Said once: the bound lets messages go while no window needs them, so it holds less than pre_trigger."""
        if self._bound_warned or self._windows.open is not None or not any(self._ring.lost_to_bound):
            return
        oldest = self._ring.oldest_ns()
        if oldest is None:
            return
        self._bound_warned = True
        held = (now_ns - oldest) / 1e9
        self.context.logger.warning(
            f"measurement {self.context.name}: max_memory_mb ({self.params.max_memory_mb:g} MiB) holds only "
            f"{held:.1f} s of the topics at their current rates, less than pre_trigger ({self.params.pre_trigger:g} "
            "s): incidents start later than asked (said once)"
        )

    def collect(self) -> dict[str, Any] | None:
        return None  # conditions_trigger: the server polls, it never collects

    # -- writing ---------------------------------------------------------------------------------
    def _snapshot(self, incident: Incident, write_at_ns: int) -> _Closing:
        """The window's messages taken so far: from now on the ring may let them go (the snapshot keeps them)."""
        self._ring.hold_from_ns = NEVER
        entries = self._ring.window(incident.start_ns, incident.end_ns)
        lost = self._ring.take_lost_in_window()
        held = self._ring.writing(incident.start_ns, incident.end_ns, entries)
        return _Closing(incident, entries, any(lost), lost, write_at_ns, held)

    def _close(self, closing: _Closing) -> None:
        job, sample, base = self._prepare(closing)
        self.writing += 1
        self.context.worker.submit(job, functools.partial(self._written, closing, sample, base))

    def _prepare(self, closing: _Closing) -> tuple[Callable[[], Written], dict[str, Any], str]:
        """What writes the incident's file, its record (without the file's size), and the path reserved.

        Messages of the window taken after the snapshot (received before its end, still queued then) join it.
        """
        incident = closing.incident
        taken = {id(e) for e in closing.entries}
        late = [e for e in self._ring.between(incident.start_ns, incident.end_ns) if id(e) not in taken]
        entries = closing.entries = closing.entries + late
        closing.held.held.update(id(e) for e in late)
        channels = [t.channel for t in self._topics]
        locations = file_locations(self.context.paths, self.params.save_path, incident.start_ns / 1e9)
        locations = self._reserved.reserve(locations, (_SUFFIX,))
        local, remote = locations.with_suffix(_SUFFIX)
        # (late messages the ring let go before they could join: lost to the window too)
        lost = [a + b for a, b in zip(closing.lost, closing.held.lost, strict=True)]
        sample = self._sample(incident, entries, lost, closing.cut or any(lost), local, remote)
        job = functools.partial(write_mcap, local, channels, entries, self.params.compression, self._definitions.get)
        return job, sample, locations.local

    def _sample(
        self, incident: Incident, entries: list[Entry], lost: list[int], cut: bool, local: str, remote: dict[str, str]
    ) -> dict[str, Any]:
        counts = [0] * len(self._topics)
        sizes = [0] * len(self._topics)
        for _, _, index, data in entries:
            counts[index] += 1
            sizes[index] += len(data)
        in_transport, unchecked = self._transport_losses(incident.start_ns, incident.end_ns)
        topics = []
        for index, topic in enumerate(self._topics):
            entry: dict[str, Any] = {
                "topic": topic.name,
                "type": topic.typename,
                "messages": counts[index],
                "bytes": sizes[index],
                "lost_to_memory_bound": lost[index],
                "lost_in_transport": in_transport[index],
                "absent": self._absent(index),
            }
            if unchecked[index]:
                entry["transport_losses_unchecked"] = True
            topics.append(entry)
        absent = [t.name for i, t in enumerate(self._topics) if self._absent(i)]
        if absent and not self._absent_warned:
            self._absent_warned = True
            self.context.logger.warning(
                f"measurement {self.context.name}: never seen, recorded as absent: {', '.join(absent)} (said once)"
            )
        sample: dict[str, Any] = {
            "start": incident.start_ns / 1e9,
            "end": incident.end_ns / 1e9,
            "triggers": [{"time": t.time_ns / 1e9, "reason": t.reason} for t in incident.triggers],
            "topics": topics,
            "messages": sum(counts),
            "cut_by_memory_bound": cut,
            "local_paths": {"mcap": local},
        }
        if remote:
            sample["remote_paths"] = {key: {"mcap": path} for key, path in remote.items()}
        return sample

    def _absent(self, index: int) -> bool:
        """Never seen: no type known, or subscribed early (``types``) and no publisher nor message since."""
        topic = self._topics[index]
        return (not topic.typename or topic.early) and not self._received[index]

    def _note_written(self, sample: dict[str, Any], written: Written) -> None:
        """The file's size in the record, and the types whose definition it lacks (warned once each)."""
        sample["size"] = written.size
        for entry in sample["topics"]:
            if entry["type"] in written.without_definition:
                entry["definition_missing"] = True
        for typename in set(written.without_definition) - self._without_definition_warned:
            self._without_definition_warned.add(typename)
            self.context.logger.warning(
                f"measurement {self.context.name}: no message definition found for {typename}: its messages are "
                "in the files without a schema (said once)"
            )

    def _written(self, closing: _Closing, sample: dict[str, Any], base: str, outcome: Outcome[Written]) -> None:
        self.writing -= 1
        self._reserved.release(base)
        try:
            written = outcome.get()
        except Exception as exc:
            self.write_errors += 1
            closing.failures += 1
            if closing.failures < WRITE_TRIES:
                closing.write_at_ns = time.time_ns() + WRITE_RETRY_NS
                self._retrying.append(closing)
                self._save_log.event(1, f"{sample['local_paths']['mcap']}: {exc} (kept, tried again)")
            else:
                self.incidents_dropped += 1
                self._ring.written(closing.held)
                self._save_log.event(
                    1, f"{sample['local_paths']['mcap']}: {exc}; dropped after {WRITE_TRIES} tries: {sample}"
                )
            self._set_timers()
            return
        self._ring.written(closing.held)
        self._note_written(sample, written)
        self.incidents += 1
        self.context.emit(sample, stamp_ns=int(sample["triggers"][0]["time"] * 1e9))
        self._set_timers()

    def counters(self) -> dict[str, int]:
        w = self._windows
        return {
            "messages": sum(self._received),
            "ring_bytes": self._ring.bytes,
            "writing_bytes": self._ring.held_out,
            "lost_to_bound": sum(self._ring.lost_to_bound),
            "lost_in_transport": sum(self._lost_in_transport),
            "triggers": w.triggers,
            "triggers_in_cooldown": w.in_cooldown,
            "triggers_over_hourly_limit": w.over_hourly_limit,
            "incidents": self.incidents,
            "write_errors": self.write_errors,
            "incidents_unpublished": self.unpublished,
            "incidents_being_written": self.writing,
            "incidents_dropped": self.incidents_dropped,
        }
