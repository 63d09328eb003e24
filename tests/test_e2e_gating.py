"""Conditions gating measurements in real `dc-bringup` runs, observed as a user observes them.

The test drives the data from its own rclpy node, joined to the run's ROS domain: it publishes the
records a StringStamped measurement forwards, the switch a `topic:` condition judges, and the
odometry Moving watches. Records are read on the Stdout destination; condition states on
`/dc/condition/<id>`.
"""

from __future__ import annotations

import json
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
import rclpy
from nav_msgs.msg import Odometry
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from dc_interfaces.msg import Condition as ConditionMsg
from dc_interfaces.msg import StringStamped
from tests.bringup_util import Bringup

pytestmark = pytest.mark.e2e

DEADLINE_S = 20.0
RELIABLE = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
# What a late subscriber needs to receive the current state of a condition at once.
CONDITION_STATE_QOS = QoSProfile(
    depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL
)

DESTINATION = """
destination_server:
  ros__parameters:
    flb:
      flush: 0.1
      storage_path: "var/buffer"
    destination_plugins: ["stdout"]
    stdout:
      plugin: "dc_destinations/Stdout"
      inputs: {inputs}
"""


class RosPeer:
    """This test's own ROS node in the run's domain: a separate DDS participant, as another process' node."""

    def __init__(self, run: Bringup) -> None:
        self.run = run
        self.context = Context()
        rclpy.init(context=self.context, domain_id=run.domain_id)
        self.node = rclpy.create_node(f"gating_test_{uuid.uuid4().hex[:8]}", context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.states: dict[str, list[bool]] = {}

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)

    def spin_until(
        self, done: Callable[[], bool], what: str, step: Callable[[], None] = lambda: None, timeout: float = DEADLINE_S
    ) -> None:
        """Spin (running ``step`` every turn) until ``done``; fail with the run's output otherwise."""
        deadline = time.monotonic() + timeout
        while not done():
            if time.monotonic() > deadline:
                raise AssertionError(
                    f"timed out after {timeout} s waiting for {what}\n--- stdout ---\n"
                    + "\n".join(self.run.stdout[-30:])
                    + "\n--- stderr ---\n"
                    + "\n".join(self.run.stderr[-60:])
                )
            step()
            self.executor.spin_once(timeout_sec=0.05)

    def spin_for(self, seconds: float, step: Callable[[], None] = lambda: None) -> None:
        """Keep the run going for a while: to show that something does *not* happen."""
        until = time.monotonic() + seconds
        self.spin_until(lambda: time.monotonic() > until, f"{seconds} s", step, timeout=seconds + 1)

    def publisher(self, msg_type: Any, topic: str) -> Any:
        """A reliable publisher, returned once DC's subscription to it has matched."""
        publisher = self.node.create_publisher(msg_type, topic, RELIABLE)
        self.spin_until(lambda: publisher.get_subscription_count() >= 1, f"DC to subscribe to {topic}")
        return publisher

    def watch_condition(self, condition_id: str) -> list[bool]:
        """Every state received on /dc/condition/<id>, in order (the list fills while spinning)."""
        received = self.states.setdefault(condition_id, [])

        def on_state(msg: Any) -> None:
            received.append(bool(msg.data))

        self.node.create_subscription(ConditionMsg, f"/dc/condition/{condition_id}", on_state, CONDITION_STATE_QOS)
        return received


@contextmanager
def ros_peer(run: Bringup) -> Iterator[RosPeer]:
    node = RosPeer(run)
    try:
        yield node
    finally:
        node.close()


def string_stamped(record: dict[str, Any]) -> StringStamped:
    msg = StringStamped()
    msg.header.stamp.sec = 1_700_000_000
    msg.data = json.dumps(record)
    return msg


def write_params(tmp_path: Path, measurement_server: str, inputs: list[str]) -> Path:
    params = tmp_path / "params.yaml"
    params.write_text(measurement_server + DESTINATION.format(inputs=json.dumps(inputs)))
    return params


def named(name: str) -> Callable[[dict[str, Any]], bool]:
    return lambda record: record.get("name") == name


# --- if_all / if_any / if_none ------------------------------------------------------------------

GATED_BY_LISTS = """
measurement_server:
  ros__parameters:
    measurement_plugins: ["all_of", "any_of", "none_of"]
    condition_plugins: ["busy", "alarm", "docked"]
    busy:
      plugin: "dc_conditions/IntegerSuperior"
      key: "status/load"
      value: 5
      include_value: false
    alarm:
      plugin: "dc_conditions/Exist"
      key: "alarm"
    docked:
      plugin: "dc_conditions/BoolEqual"
      key: "docked"
      value: true
    all_of:
      plugin: "dc_measurements/StringStamped"
      topic: "/robot/state"
      timer_based: false
      tags: ["stdout"]
      if_all_conditions: ["busy", "docked"]
    any_of:
      plugin: "dc_measurements/StringStamped"
      topic: "/robot/state"
      timer_based: false
      tags: ["stdout"]
      if_any_conditions: ["busy", "alarm"]
    none_of:
      plugin: "dc_measurements/StringStamped"
      topic: "/robot/state"
      timer_based: false
      tags: ["stdout"]
      if_none_conditions: ["alarm", "docked"]
"""

# (record, busy, alarm, docked) — the expected state of each condition is written beside it.
STATES: list[tuple[dict[str, Any], bool, bool, bool]] = [
    ({"seq": 0, "status": {"load": 1}, "docked": False}, False, False, False),
    ({"seq": 1, "status": {"load": 9}, "docked": True}, True, False, True),
    ({"seq": 2, "status": {"load": 9}, "docked": False, "alarm": "bumper"}, True, True, False),
    ({"seq": 3, "status": {"load": 3}, "docked": True, "alarm": None}, False, True, True),
    ({"seq": 4, "status": {"load": 6}, "docked": "true"}, True, False, False),  # a string is not a bool
    ({"seq": 5, "status": {"load": 5}, "docked": False}, False, False, False),  # 5 is not > 5
    ({"seq": 6, "docked": True}, False, False, True),  # no load: busy is inactive, nothing crashes
    ({"seq": 7, "status": {"load": 10.0}, "docked": True}, True, False, True),  # 10.0 is the integer 10
]


@pytest.mark.usefixtures("bringup_mode")
def test_only_records_satisfying_if_all_if_any_if_none_arrive(tmp_path: Path) -> None:
    expected = {
        "all_of": {r["seq"] for r, busy, _, docked in STATES if busy and docked},
        "any_of": {r["seq"] for r, busy, alarm, _ in STATES if busy or alarm},
        "none_of": {r["seq"] for r, _, alarm, docked in STATES if not alarm and not docked},
    }
    assert expected == {"all_of": {1, 7}, "any_of": {1, 2, 3, 4, 7}, "none_of": {0, 4, 5}}
    inputs = [f"/dc/measurement/{name}" for name in expected]
    with Bringup(write_params(tmp_path, GATED_BY_LISTS, inputs), tmp_path / "home") as run:
        run.wait_ready()
        with ros_peer(run) as ros:
            publisher = ros.publisher(StringStamped, "/robot/state")
            # One subscription per measurement: wait until all three are there.
            ros.spin_until(lambda: publisher.get_subscription_count() >= 3, "three StringStamped subscriptions")
            for record, *_ in STATES:
                publisher.publish(string_stamped(record))

            def all_arrived() -> bool:
                got = {name: {r["seq"] for r in run.records(named(name))} for name in expected}
                return all(got[name] >= seqs for name, seqs in expected.items())

            ros.spin_until(all_arrived, f"the records {expected}")
            # Records of one topic keep their order: the last expected seq of each has arrived, so
            # any record wrongly let through before it has arrived too.
            for name, seqs in expected.items():
                arrived = [r["seq"] for r in run.records(named(name))]
                assert arrived == sorted(seqs), f"{name}: {arrived}"

            # The last sample judged (seq 7) left busy and docked active, alarm inactive: a
            # subscriber joining now gets each current state at once (transient local).
            late = {cid: ros.watch_condition(cid) for cid in ("busy", "alarm", "docked")}
            ros.spin_until(lambda: all(late.values()), "the current state of every condition")
            assert {cid: states[-1] for cid, states in late.items()} == {"busy": True, "alarm": False, "docked": True}
    assert not any("Traceback" in line for line in run.stderr), "\n".join(run.stderr)


# --- condition_max_measurements re-arms; a condition judging another topic ----------------------

GATED_BY_SWITCH = """
measurement_server:
  ros__parameters:
    measurement_plugins: ["dummy"]
    condition_plugins: ["switch_on"]
    switch_on:
      plugin: "dc_conditions/BoolEqual"
      topic: "/test/switch"
      key: "on"
      value: true
    dummy:
      plugin: "dc_measurements/Dummy"
      record: '{"message": "gated"}'
      polling_interval: 100
      condition_max_measurements: 2
      if_all_conditions: ["switch_on"]
      tags: ["stdout"]
"""


def test_condition_max_measurements_rearms_when_the_condition_falls(tmp_path: Path) -> None:
    params = write_params(tmp_path, GATED_BY_SWITCH, ["/dc/measurement/dummy"])
    with Bringup(params, tmp_path / "home") as run:
        run.wait_ready()
        with ros_peer(run) as ros:
            states = ros.watch_condition("switch_on")
            switch = ros.publisher(StringStamped, "/test/switch")
            # No switch record yet: the condition is inactive and says so.
            ros.spin_until(lambda: states == [False], "the initial state false")
            assert run.records() == []

            for episode in (1, 2):
                switch.publish(string_stamped({"on": True}))
                ros.spin_until(lambda: states[-1] is True, "the condition to become active")
                run.wait_records(2 * episode, timeout=DEADLINE_S)
                # Ten more polls while still active: the episode's two records were its last.
                ros.spin_for(1.0)
                assert len(run.records()) == 2 * episode

                switch.publish(string_stamped({"on": False}))
                # The state falls on the first poll that sees the record: the episode is over.
                ros.spin_until(lambda: states[-1] is False, "the condition to fall")
            assert states == [False, True, False, True, False]
            records = run.records()
    assert len(records) == 4
    assert all(r["message"] == "gated" and r["name"] == "dummy" for r in records)


# --- Moving: one record per stop -----------------------------------------------------------------

ONE_RECORD_PER_STOP = """
measurement_server:
  ros__parameters:
    measurement_plugins: ["stop_snapshot"]
    condition_plugins: ["moving"]
    moving:
      plugin: "dc_conditions/Moving"
      odom_topic: "/test/odom"
      speed_threshold: 0.2
      count_limit: 3
      count_hysteresis: 2
    stop_snapshot:
      plugin: "dc_measurements/Uptime"
      polling_interval: 100
      condition_max_measurements: 1
      if_none_conditions: ["moving"]
      tags: ["stdout"]
"""


def odometry(speed: float) -> Odometry:
    message = Odometry()
    message.twist.twist.linear.x = speed
    return message


@pytest.mark.usefixtures("bringup_mode")
def test_moving_robot_stops_give_one_record_per_stop(tmp_path: Path) -> None:
    params = write_params(tmp_path, ONE_RECORD_PER_STOP, ["/dc/measurement/stop_snapshot"])
    with Bringup(params, tmp_path / "home") as run:
        run.wait_ready()
        with ros_peer(run) as ros:
            moving = ros.watch_condition("moving")
            odom = ros.publisher(Odometry, "/test/odom")

            def has_records(n: int) -> Callable[[], bool]:
                return lambda: len(run.records()) == n

            # At rest from the start: the first stop gives one record.
            ros.spin_until(has_records(1), "the record of the first stop")
            for stop in (2, 3):
                ros.spin_until(lambda: moving[-1:] == [True], "the robot to move", lambda: odom.publish(odometry(0.5)))
                assert len(run.records()) == stop - 1, "no record while moving"
                ros.spin_until(lambda: moving[-1:] == [False], "the robot to stop", lambda: odom.publish(odometry(0.0)))
                ros.spin_until(has_records(stop), f"the record of stop {stop}")
                # Still stopped for ten more polls: no second record for the same stop.
                ros.spin_for(1.0, lambda: odom.publish(odometry(0.0)))
                assert len(run.records()) == stop
    records = run.records()
    assert [r["name"] for r in records] == ["stop_snapshot"] * 3
    assert all(isinstance(r["time"], int) for r in records)
