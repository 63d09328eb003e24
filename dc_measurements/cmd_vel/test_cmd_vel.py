"""CmdVel fed with real Twist messages over DDS, in-process."""

from __future__ import annotations

import time
from collections.abc import Iterator

import pytest
import rclpy
from geometry_msgs.msg import Twist, TwistStamped
from rclpy.context import Context
from rclpy.node import Node
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


def twist_stamped(vx: float, wz: float, stamp_ns: int) -> TwistStamped:
    message = TwistStamped()
    message.header.stamp.sec, message.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    message.header.frame_id = "base_link"
    message.twist = twist(vx, 0.0, wz)
    return message


STAMP_NS = 1_700_000_000_123_000_000


@pytest.fixture
def controller() -> Iterator[Node]:
    """The robot's controller, in a context of its own: one DDS participant cannot have a topic under two types."""
    context = Context()
    rclpy.init(context=context)
    node = rclpy.create_node(unique("controller"), context=context)
    yield node
    node.destroy_node()
    rclpy.shutdown(context=context)


@pytest.mark.parametrize("message_type", ["auto", "geometry_msgs/msg/TwistStamped"])
def test_twist_stamped_publisher_gives_the_same_record_dated_by_its_header(
    ros: Ros, controller: Node, message_type: str
) -> None:
    # A publisher that exists before configure, as diff_drive_controller's does when DC starts.
    topic = unique("/cmd_vel")
    publisher = controller.create_publisher(TwistStamped, topic, QoSProfile(depth=10))
    assert ros.spin_until(lambda: bool(ros.node.get_publishers_info_by_topic(topic)))  # discovered
    plugin = ros.start(CmdVel, {"topic": topic, "message_type": message_type})
    assert plugin.subscribed_type == "geometry_msgs/msg/TwistStamped"
    assert ros.spin_until(lambda: publisher.get_subscription_count() >= 1)
    publisher.publish(twist_stamped(0.3, 0.5, STAMP_NS))
    assert ros.spin_until(lambda: plugin.counters()["received"] == 1)
    record, stamp, _ = plugin.collect_stamped()
    assert_valid(CmdVel, record)
    assert record["linear"] == {"x": 0.3, "y": 0.0, "z": 0.0}
    assert record["angular"] == {"x": 0.0, "y": 0.0, "z": 0.5}
    assert record["computed"] == pytest.approx(0.3)
    assert set(record) == {"linear", "angular", "computed", "age"}  # the fields of a Twist's record
    assert stamp == STAMP_NS  # the record's time is the command's header stamp
    ros.harness.stop(plugin)


def test_auto_follows_a_publisher_that_appears_after_configure(ros: Ros, controller: Node) -> None:
    topic = unique("/cmd_vel")
    plugin = ros.start(CmdVel, {"topic": topic})
    # No publisher yet: Twist, the type of teleop and of the original.
    assert plugin.subscribed_type == "geometry_msgs/msg/Twist"
    publisher = controller.create_publisher(TwistStamped, topic, QoSProfile(depth=10))
    # The next poll without a new message looks at the graph and subscribes to TwistStamped.
    assert ros.spin_until(
        lambda: plugin.collect() is None and plugin.subscribed_type == "geometry_msgs/msg/TwistStamped"
    )
    assert ros.spin_until(lambda: publisher.get_subscription_count() >= 1)
    publisher.publish(twist_stamped(0.2, 0.0, STAMP_NS))
    assert ros.spin_until(lambda: plugin.counters()["received"] == 1)
    record, stamp, _ = plugin.collect_stamped()
    assert record["linear"]["x"] == 0.2
    assert stamp == STAMP_NS
    assert "subscribed to it instead of geometry_msgs/msg/Twist" in " ".join(
        ros.harness.context(plugin).logger.at("info")
    )
    ros.harness.stop(plugin)


def test_auto_keeps_twist_for_a_twist_publisher_and_dates_by_the_poll(ros: Ros, controller: Node) -> None:
    topic = unique("/cmd_vel")
    publisher = controller.create_publisher(Twist, topic, QoSProfile(depth=10))
    assert ros.spin_until(lambda: bool(ros.node.get_publishers_info_by_topic(topic)))
    plugin = ros.start(CmdVel, {"topic": topic})
    assert plugin.subscribed_type == "geometry_msgs/msg/Twist"
    assert ros.spin_until(lambda: publisher.get_subscription_count() >= 1)
    publisher.publish(twist(0.4))
    assert ros.spin_until(lambda: plugin.counters()["received"] == 1)
    record, stamp, _ = plugin.collect_stamped()
    assert record["linear"]["x"] == 0.4
    assert stamp is None  # a Twist has no time of its own: the server dates the record
    assert plugin.collect() is None
    assert plugin.subscribed_type == "geometry_msgs/msg/Twist"
    ros.harness.stop(plugin)


def test_message_type_is_validated() -> None:
    from dc_core.errors import ConfigError
    from dc_core.params import parse_params
    from dc_measurements.cmd_vel import CmdVelParams

    with pytest.raises(ConfigError, match=r"cmd_vel\.message_type"):
        parse_params(CmdVelParams, {"message_type": "Twist"}, "cmd_vel")
