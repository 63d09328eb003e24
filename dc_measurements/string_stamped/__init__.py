"""StringStamped measurement: records that other ROS 2 nodes publish, forwarded through DC."""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Any

from dc_core.errors import PluginError
from dc_core.handoff import forwarding
from dc_core.logs import BurstLog
from dc_core.measurement import Measurement
from dc_core.params import param
from dc_core.records import MalformedRecord, parse_record
from dc_core.sequence_numbers import TopicWriters
from dc_core.stamped_cdr import read_stamped_record
from dc_core.topics import ros_topic, topic_param

_LOGGED_TEXT = 2000
# Malformed records logged one by one at the start of a burst; the rest are counted in a summary.
_MALFORMED_LINES_PER_BURST = 10


@dataclass(frozen=True, kw_only=True)
class StringStampedParams:
    topic: str = topic_param(
        doc="Input topic (dc_interfaces/msg/StringStamped) where your nodes publish ('-' is read as '_')",
    )
    timer_based: bool = param(
        True,
        doc="true: publish the latest record at every polling interval (records arriving faster are "
        "replaced, and counted as `replaced`); false: every record as it arrives",
    )
    qos_depth: int = param(100, minimum=1, doc="Subscription queue depth")
    transient_local: bool = param(
        False,
        doc="true: a transient-local subscription, made at activation, which also gets the last records a "
        "latching publisher sent before it (destination_server's dc/destination_health); only transient-local "
        "publishers match it. false: volatile, any reliable publisher matches",
    )


class StringStampedInput(Measurement[StringStampedParams]):
    """Forwards JSON records that your own nodes publish as dc_interfaces/StringStamped."""

    schema_file = None  # the records are your nodes': give them a schema with json_schema_path
    samples_are_parsed_json = True  # each sample is parse_record's

    def __init__(self, context: Any, params: Any) -> None:
        super().__init__(context, params)
        self._lock = threading.Lock()
        self._latest: tuple[dict[str, Any], int, str] | None = None
        self._subscription: Any = None
        self._topic = ""
        self._loss_log_timer: Any = None
        self._writers = TopicWriters()
        self._loss_log: BurstLog | None = None
        self._malformed_log: BurstLog | None = None
        self._replaced_log: BurstLog | None = None
        self.malformed = 0
        # Records a newer one replaced before a poll published them (timer_based: true).
        self.replaced = 0
        # Records your nodes published that never reached this subscription (DDS overwrote them in
        # a queue of qos_depth while the server was busy): seen as jumps in a publisher's numbers.
        self.lost = 0

    @property
    def timer_driven(self) -> bool:
        return bool(self.params.timer_based)

    def on_configure(self) -> None:
        node = self.context.node
        if node is None:
            raise PluginError("StringStamped needs a ROS node")
        topic = ros_topic(self.params.topic)
        if topic != self.params.topic:
            self.context.logger.warning(
                f"topic {self.params.topic!r} is not a valid ROS 2 name: listening on {topic!r}"
            )
        self._topic = topic
        self._writers = TopicWriters()
        self._loss_log = BurstLog(
            self.context.logger.error, f"measurement {self.context.name}: records lost before measurement_server"
        )
        self._malformed_log = BurstLog(
            self.context.logger.error,
            f"measurement {self.context.name}: malformed records on {topic} not published",
            each=_MALFORMED_LINES_PER_BURST,
        )
        self._replaced_log = BurstLog(
            self.context.logger.warning,
            f"measurement {self.context.name}: records on {topic} replaced by a newer one before a poll published "
            "them (timer_based: true keeps the latest per polling_interval; timer_based: false forwards every record)",
        )
        self._loss_log_timer = node.create_timer(1.0, self._tick_logs)
        if not self.params.transient_local:
            self._subscribe()

    def _subscribe(self) -> None:
        from rclpy.qos import DurabilityPolicy, QoSProfile

        from dc_interfaces.msg import StringStamped

        durability = DurabilityPolicy.TRANSIENT_LOCAL if self.params.transient_local else DurabilityPolicy.VOLATILE
        self._subscription = self.context.subscribe(
            StringStamped, self._topic, self._on_message, QoSProfile(depth=self.params.qos_depth, durability=durability)
        )
        # Taken as the bytes DDS delivered, read without building the message's Python objects.
        self._subscription.raw = True

    def _unsubscribe(self) -> None:
        if self._subscription is not None:
            self.context.unsubscribe(self._subscription)
            self._subscription = None

    def on_activate(self) -> None:
        # Not at configure: the latched records arrive as soon as the subscription matches, and the
        # server publishes nothing before it is active (they would be dropped, and not sent again).
        if self.params.transient_local:
            self._subscribe()

    def on_deactivate(self) -> None:
        # Made again at the next activation, which then gets the latest latched record again.
        if self.params.transient_local:
            self._unsubscribe()

    def on_cleanup(self) -> None:
        self._unsubscribe()
        if self._loss_log_timer is not None:
            self.context.node.destroy_timer(self._loss_log_timer)
            self._loss_log_timer = None

    def _tick_logs(self) -> None:
        for log in (self._loss_log, self._malformed_log, self._replaced_log):
            if log is not None:
                log.tick()

    def _on_message(self, serialised: bytes, info: Any) -> None:
        seq = info.get("publication_sequence_number") if info else None
        if not isinstance(seq, int) or seq <= 0:
            seq = 0
        if seq:
            skipped = self._writers.observe(seq)
            if skipped:
                self.lost += skipped
                assert self._loss_log is not None
                self._loss_log.event(
                    skipped,
                    f"{self._topic}: publication sequence numbers {seq - skipped}..{seq - 1} never arrived;"
                    f" the queues, qos_depth {self.params.qos_depth} and the publisher's depth, overflowed",
                )
        stamp_ns, text, group_key = read_stamped_record(serialised)
        try:
            record = parse_record(text)
        except MalformedRecord as exc:
            self.malformed += 1
            assert self._malformed_log is not None
            self._malformed_log.event(1, f"{exc}; record: {text[:_LOGGED_TEXT]!r}")
            return
        if not self.timer_driven:
            forwarding(seq)  # a restart of measurement_server in between is counted downstream
            try:
                self.context.emit(record, stamp_ns=stamp_ns or None, group_key=group_key or None)
            finally:
                forwarding(0)
            return
        with self._lock:
            replaced = self._latest is not None
            self._latest = (record, stamp_ns, group_key)
        if replaced:
            self.replaced += 1
            assert self._replaced_log is not None
            self._replaced_log.event(1, "a newer record arrived before the next poll")

    def counters(self) -> dict[str, int]:
        return {"malformed": self.malformed, "lost": self.lost, "replaced": self.replaced}

    def collect_stamped(self) -> tuple[dict[str, Any] | None, int | None, str | None]:
        # Each received record is published once: the original re-published the last one at every tick.
        with self._lock:
            latest, self._latest = self._latest, None
        if latest is None:
            return None, None, None
        record, stamp_ns, group_key = latest
        return record, stamp_ns or None, group_key or None

    def collect(self) -> dict[str, Any] | None:
        return self.collect_stamped()[0]
