"""``dc replay BAG``: play a rosbag2 recording (SQLite3 or MCAP) to ROS 2 topics, as ``ros2 bag play`` would.

ros2cli and rosbag2_py are not on PyPI; the ``rosbags`` package reads both storage formats without
ROS. Messages are published as the bag holds them (serialised CDR, no decoding), at the recorded
pace times ``--rate``, with ``/clock`` following the bag's time so that DC started with
``use_sim_time`` sees the robot's time. A topic whose type is not installed here (a robot's own
interface package) cannot be published: it is skipped with one warning.
"""

from __future__ import annotations

import importlib
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dc_core.errors import DcError
from dc_core.logs import Logger

# Bag time on /clock at least this often (wall time), so sim-time timers between messages fire on time.
CLOCK_PERIOD_S = 0.01
QUEUE_DEPTH = 100
# At the bag's end, before the player returns (and its node goes): how long the last messages may take
# to be acknowledged, and how long the bag's last /clock is repeated (wall time).
END_ACK_TIMEOUT_S = 5.0
END_CLOCK_HOLD_S = 0.5


class ReplayError(DcError):
    """A bag that cannot be replayed (missing, unreadable, nothing to play)."""


@dataclass(frozen=True)
class ReplayOptions:
    rate: float = 1.0
    loop: bool = False
    topics: tuple[str, ...] = ()
    clock: bool = True
    delay_s: float = 1.0
    # Topics whose publisher must be matched with that many subscriptions before the first message.
    wait_for: tuple[tuple[str, int], ...] = ()
    wait_timeout_s: float = 30.0


@dataclass
class ReplayReport:
    published: dict[str, int] = field(default_factory=dict)
    skipped: dict[str, str] = field(default_factory=dict)  # topic -> its type
    loops: int = 0


def message_class(msgtype: str) -> Any:
    """The installed Python class of ``pkg/msg/Name``, or None."""
    package, _, name = msgtype.partition("/msg/")
    if not package or not name:
        return None
    try:
        return getattr(importlib.import_module(f"{package}.msg"), name)
    except (ImportError, AttributeError):
        return None


def _recorded_qos(connection: Any) -> Any:
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    profiles = getattr(connection.ext, "offered_qos_profiles", None) or []
    latched = any(getattr(p.durability, "name", "") == "TRANSIENT_LOCAL" for p in profiles)
    # Reliable matches reliable and best-effort subscribers; the publishers of a latched topic
    # (/tf_static, /map) keep it for subscribers that come later, as the robot's did.
    return QoSProfile(
        depth=QUEUE_DEPTH,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
    )


class BagPlayer:
    """Publishes one bag's messages from a node; :meth:`play` blocks until the end or ``stop``."""

    def __init__(self, node: Any, bag: str | Path, options: ReplayOptions, logger: Logger) -> None:
        from rosbags.rosbag2 import Reader

        self.node = node
        self.options = options
        self.logger = logger
        self.report = ReplayReport()
        path = Path(bag)
        if not path.exists():
            raise ReplayError(f"no bag at {path}")
        try:
            self.reader = Reader(path)
            self.reader.open()
        except Exception as exc:  # rosbags raises its own errors for every unreadable bag
            raise ReplayError(f"cannot read the bag {path}: {exc}") from exc
        self._publishers: dict[int, Any] = {}
        self._connections: list[Any] = []
        for connection in self.reader.connections:
            if options.topics and connection.topic not in options.topics:
                continue
            cls = message_class(connection.msgtype)
            if cls is None:
                if connection.topic not in self.report.skipped:
                    self.report.skipped[connection.topic] = connection.msgtype
                    logger.warning(
                        f"{connection.topic}: type {connection.msgtype} is not installed here; topic skipped"
                    )
                continue
            self._publishers[connection.id] = node.create_publisher(cls, connection.topic, _recorded_qos(connection))
            self._connections.append(connection)
            self.report.published.setdefault(connection.topic, 0)
        missing = [t for t in options.topics if t not in self.report.published and t not in self.report.skipped]
        if missing:
            logger.warning(f"not in the bag: {', '.join(missing)}")
        if not self._connections:
            raise ReplayError(f"nothing to replay in {path}: no topic selected whose type is installed")
        self._clock_publisher: Any = None
        if options.clock:
            from rosgraph_msgs.msg import Clock

            self._clock_publisher = node.create_publisher(Clock, "/clock", QUEUE_DEPTH)
        self._last_clock_ns = 0

    def close(self) -> None:
        self.reader.close()

    @property
    def duration_s(self) -> float:
        return float(self.reader.duration) / 1e9

    def _publish_clock(self, bag_ns: int) -> None:
        if self._clock_publisher is None:
            return
        from rosgraph_msgs.msg import Clock

        # Never backwards within a pass (a loop resets _last_clock_ns): DC clears its TF history when
        # its clock jumps back, as tf2_ros does, so only a real restart of the bag may do that.
        bag_ns = max(bag_ns, self._last_clock_ns)
        message = Clock()
        message.clock.sec, message.clock.nanosec = divmod(bag_ns, 1_000_000_000)
        self._clock_publisher.publish(message)
        self._last_clock_ns = bag_ns

    def _wait_for_subscribers(self, stop: threading.Event) -> bool:
        """Wait until the topics of ``wait_for`` are matched with enough subscriptions; False if stopped."""
        publishers = {c.topic: self._publishers[c.id] for c in self._connections}
        for topic, _ in self.options.wait_for:
            if topic not in publishers:
                raise ReplayError(f"--wait-for {topic}: the bag has no such topic to replay")
        deadline = time.monotonic() + self.options.wait_timeout_s
        while True:
            missing = [
                f"{topic} ({publishers[topic].get_subscription_count()} of {count})"
                for topic, count in self.options.wait_for
                if publishers[topic].get_subscription_count() < count
            ]
            if not missing:
                return True
            if time.monotonic() > deadline:
                raise ReplayError(
                    f"subscribers not matched after {self.options.wait_timeout_s:g} s: {', '.join(missing)}"
                )
            if stop.wait(0.02):
                return False

    def play(self, stop: threading.Event) -> ReplayReport:
        if not self._wait_for_subscribers(stop):
            return self.report
        if self.options.delay_s and stop.wait(self.options.delay_s):  # discovery: let subscribers match first
            return self.report
        while True:
            if not self._play_once(stop) or stop.is_set():
                return self.report
            if not self.options.loop:
                self._deliver_the_end(stop)
                return self.report
            self.report.loops += 1
            self._last_clock_ns = 0  # time starts over: /clock jumps back, as ros2 bag play --loop does

    def _deliver_the_end(self, stop: threading.Event) -> None:
        """The bag's last messages and its last /clock reach the subscribers before the node goes.

        Publishing is asynchronous: a player that returned at once could take the bag's last messages
        down with its node on a loaded machine (DC's last polls then see the robot short of its end).
        rclpy's /clock subscription is best-effort, so the last /clock is repeated for a moment."""
        from rclpy.duration import Duration

        deadline = time.monotonic() + END_ACK_TIMEOUT_S  # for all of them: a reader that died acks nothing
        for publisher in self._publishers.values():
            publisher.wait_for_all_acked(Duration(seconds=max(deadline - time.monotonic(), 0.0)))
        if self._clock_publisher is None:
            return
        end = time.monotonic() + END_CLOCK_HOLD_S
        while time.monotonic() < end and not stop.wait(CLOCK_PERIOD_S * 10):
            self._publish_clock(self._last_clock_ns)

    def _play_once(self, stop: threading.Event) -> bool:
        """One pass over the bag; False when stopped before its end."""
        rate = self.options.rate
        start_wall = time.monotonic()
        start_bag = int(self.reader.start_time)
        next_clock = start_wall
        for connection, bag_ns, raw in self.reader.messages(connections=self._connections):
            due = start_wall + (bag_ns - start_bag) / 1e9 / rate
            while True:
                now = time.monotonic()
                if now >= next_clock:
                    # A player running late does not run the clock past the message it still owes.
                    self._publish_clock(min(bag_ns, start_bag + int((now - start_wall) * rate * 1e9)))
                    next_clock = now + CLOCK_PERIOD_S
                if now >= due:
                    break
                if stop.wait(min(due, next_clock) - now):
                    return False
            self._publish_clock(bag_ns)
            self._publishers[connection.id].publish(bytes(raw))
            self.report.published[connection.topic] += 1
        return True


def replay(bag: str, options: ReplayOptions, stop: threading.Event, logger: Logger | None = None) -> ReplayReport:
    """Play ``bag`` from a node of its own (rclpy initialised by the caller)."""
    import rclpy

    node = rclpy.create_node("dc_replay")
    log: Logger = logger or node.get_logger()
    player = BagPlayer(node, bag, options, log)
    try:
        log.info(
            f"replaying {bag}: {len(player.report.published)} topics, {player.duration_s:.1f} s at {options.rate:g}x"
            + (", /clock on" if options.clock else "")
            + (", looping" if options.loop else "")
        )
        report = player.play(stop)
        log.info("published " + ", ".join(f"{topic} {n}" for topic, n in sorted(report.published.items())))
        return report
    finally:
        player.close()
        node.destroy_node()


def wait_for_argument(values: Sequence[str] | None) -> tuple[tuple[str, int], ...]:
    """``--wait-for /tf=3 /odom`` (a count of 1 when none is given)."""
    pairs = []
    for value in values or ():
        topic, _, count = value.partition("=")
        try:
            pairs.append((topic, int(count) if count else 1))
        except ValueError:
            raise ReplayError(f"--wait-for {value!r}: expected TOPIC or TOPIC=COUNT") from None
    return tuple(pairs)


def topics_argument(values: Sequence[str] | None) -> tuple[str, ...]:
    """``--topics /odom /tf`` or ``--topics /odom,/tf``."""
    return tuple(t for value in values or () for t in value.split(",") if t)
