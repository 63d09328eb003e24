"""Position from real /tf and /tf_static messages over DDS, in-process."""

from __future__ import annotations

import math
import time
from collections.abc import Iterator

import pytest
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from tf2_msgs.msg import TFMessage

from dc_measurements.position import Position
from tests.measurement_helpers import assert_valid
from tests.robot_helpers import Ros, ros_session, tf_message, transform, unique

STATIC_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


@pytest.fixture
def ros() -> Iterator[Ros]:
    with ros_session("position") as session:
        yield session


def test_position_follows_the_chain_of_frames(ros: Ros) -> None:
    odom, footprint, base = unique("odom"), unique("base_footprint"), unique("base_link")
    # A static published before the measurement starts still arrives (TRANSIENT_LOCAL), as on a robot.
    static = ros.node.create_publisher(TFMessage, "/tf_static", STATIC_QOS)
    static.publish(tf_message(transform(footprint, base, 0.1, 0.0, 0.0)))
    plugin = ros.start(Position, {"global_frame": odom, "robot_base_frame": base})
    dynamic = ros.publisher(TFMessage, "/tf", QoSProfile(depth=10))
    dynamic.publish(tf_message(transform(odom, footprint, 1.0, 2.0, math.pi / 2, stamp_ns=1_000_000_000)))
    record: dict[str, float] | None = None

    def arrived() -> bool:
        nonlocal record
        record = plugin.collect()
        return record is not None

    assert ros.spin_until(arrived)
    assert record is not None
    assert_valid(Position, record)
    # base_link is 0.1 m ahead of base_footprint, which faces +y at (1, 2).
    assert record == {"x": pytest.approx(1.0), "y": pytest.approx(2.1), "yaw": pytest.approx(math.pi / 2)}
    # Dated with the transforms' time (the newest dynamic link), not the poll's: where the robot was, when.
    dynamic.publish(tf_message(transform(odom, footprint, 3.0, 2.0, math.pi / 2, stamp_ns=2_500_000_000)))
    assert ros.spin_until(lambda: plugin.buffer.latest_time(odom, base) == 2_500_000_000)
    record, stamp, _ = plugin.collect_stamped()
    assert record is not None and record["x"] == pytest.approx(3.0) and stamp == 2_500_000_000
    ros.harness.stop(plugin)


def test_no_transform_reports_nothing_after_transform_timeout_and_says_why(ros: Ros) -> None:
    plugin = ros.start(
        Position, {"global_frame": unique("map"), "robot_base_frame": unique("base"), "transform_timeout": 0.3}
    )
    started = time.monotonic()
    assert plugin.collect() is None
    assert time.monotonic() - started >= 0.3  # it waited for the transform that long
    assert plugin.counters()["no_transform"] == 1
    warnings = ros.harness.context(plugin).logger.at("warning")
    assert any("no transform from" in line and "is unknown" in line for line in warnings), warnings
    ros.harness.stop(plugin)
