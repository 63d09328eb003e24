"""CmdVel fed with real Twist messages over DDS, in-process."""

from __future__ import annotations

import time
from collections.abc import Iterator

import pytest
from geometry_msgs.msg import Twist
from rclpy.qos import QoSProfile, ReliabilityPolicy

from dc_measurements.cmd_vel import CmdVel
from tests.measurement_helpers import assert_valid
from tests.robot_helpers import Ros, ros_session, twist, unique


@pytest.fixture
def ros() -> Iterator[Ros]:
    with ros_session("velocity") as session:
        yield session


@pytest.mark.parametrize("reliability", [ReliabilityPolicy.RELIABLE, ReliabilityPolicy.BEST_EFFORT])
def test_cmd_vel_reports_the_newest_command_once(ros: Ros, reliability: ReliabilityPolicy) -> None:
    topic = unique("/cmd_vel")
    plugin = ros.start(CmdVel, {"topic": topic})
    publisher = ros.publisher(Twist, topic, QoSProfile(depth=10, reliability=reliability))
    assert plugin.collect() is None  # nothing commanded yet
    publisher.publish(twist(0.1))
    publisher.publish(twist(0.3, 0.4, 0.5))
    assert ros.spin_until(lambda: plugin.counters()["received"] == 2)
    record = plugin.collect()
    assert_valid(CmdVel, record)
    assert record["linear"] == {"x": 0.3, "y": 0.4, "z": 0.0}
    assert record["angular"] == {"x": 0.0, "y": 0.0, "z": 0.5}
    assert record["computed"] == pytest.approx(0.5)
    assert 0.0 <= record["age"] < 5.0
    # The documented choice: a poll with nothing new reports nothing.
    assert plugin.collect() is None
    ros.harness.stop(plugin)


def test_repeat_last_reports_the_last_command_again_with_its_age(ros: Ros) -> None:
    topic = unique("/cmd_vel")
    plugin = ros.start(CmdVel, {"topic": topic, "repeat_last": True})
    publisher = ros.publisher(Twist, topic, QoSProfile(depth=10))
    publisher.publish(twist(0.2))
    assert ros.spin_until(lambda: plugin.counters()["received"] == 1)
    first = plugin.collect()
    later = time.monotonic() + 0.1
    ros.spin_until(lambda: time.monotonic() > later)  # the message gets older
    again = plugin.collect()
    assert again["linear"] == first["linear"]
    assert again["age"] > first["age"]
    ros.harness.stop(plugin)


def test_cleanup_forgets_the_last_message(ros: Ros) -> None:
    topic = unique("/cmd_vel")
    plugin = ros.start(CmdVel, {"topic": topic, "repeat_last": True})
    publisher = ros.publisher(Twist, topic, QoSProfile(depth=10))
    publisher.publish(twist(0.2))
    assert ros.spin_until(lambda: plugin.counters()["received"] == 1)
    plugin.on_deactivate()
    plugin.on_cleanup()
    plugin.on_configure()
    assert plugin.collect() is None  # a reconfigured measurement does not report a command of before
    ros.harness.stop(plugin)
