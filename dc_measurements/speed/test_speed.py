"""Speed fed with real Odometry messages over DDS, in-process."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from nav_msgs.msg import Odometry
from rclpy.qos import QoSProfile, ReliabilityPolicy

from dc_measurements.speed import Speed
from tests.measurement_helpers import assert_valid
from tests.robot_helpers import Ros, odometry, ros_session, unique


@pytest.fixture
def ros() -> Iterator[Ros]:
    with ros_session("speed") as session:
        yield session


def test_speed_reports_the_odometry_twist_from_a_best_effort_publisher(ros: Ros) -> None:
    topic = unique("/odom")
    plugin = ros.start(Speed, {"odom_topic": topic})
    # Real robots publish odometry best effort: a reliable subscription would never match it.
    publisher = ros.publisher(Odometry, topic, QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT))
    publisher.publish(odometry(1.0, 2.0, 0.3, vx=-0.25, wz=0.1))
    assert ros.spin_until(lambda: plugin.counters()["received"] == 1)
    record = plugin.collect()
    assert_valid(Speed, record)
    assert record["linear"]["x"] == -0.25
    assert record["angular"]["z"] == 0.1
    assert record["computed"] == pytest.approx(0.25)  # a speed, whatever the direction
    assert plugin.collect() is None
    ros.harness.stop(plugin)


def test_a_speed_record_is_dated_with_its_odometry_stamp_and_a_repeat_by_the_poll(ros: Ros) -> None:
    topic = unique("/odom")
    plugin = ros.start(Speed, {"odom_topic": topic, "repeat_last": True})
    publisher = ros.publisher(Odometry, topic, QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT))
    publisher.publish(odometry(0.0, 0.0, 0.0, vx=0.5, stamp_ns=1_700_000_000_250_000_000))
    assert ros.spin_until(lambda: plugin.counters()["received"] == 1)
    record, stamp, _ = plugin.collect_stamped()
    assert record is not None and record["linear"]["x"] == 0.5
    assert stamp == 1_700_000_000_250_000_000  # when the robot went at that speed, not when it was polled
    repeated, stamp, _ = plugin.collect_stamped()
    assert repeated is not None and stamp is None  # repeat_last: dated by the poll, its `age` says how old
    publisher.publish(odometry(0.0, 0.0, 0.0, vx=0.2))  # unstamped: dated by the poll too
    assert ros.spin_until(lambda: plugin.counters()["received"] == 2)
    record, stamp, _ = plugin.collect_stamped()
    assert record is not None and record["linear"]["x"] == 0.2 and stamp is None
    ros.harness.stop(plugin)
