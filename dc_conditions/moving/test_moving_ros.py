"""Moving driven by real nav_msgs/msg/Odometry messages published in-process."""

from __future__ import annotations

import uuid
from collections.abc import Iterator

import pytest
from nav_msgs.msg import Odometry
from rclpy.qos import QoSProfile, ReliabilityPolicy

from dc_conditions.moving import Moving, MovingParams, linear_speed
from dc_core.params import parse_params
from dc_core.testing import FakeContext
from tests.robot_helpers import Ros, ros_session


@pytest.fixture
def ros() -> Iterator[Ros]:
    with ros_session("moving") as session:
        yield session


def odometry(vx: float, vy: float = 0.0, vz: float = 0.0) -> Odometry:
    message = Odometry()
    message.twist.twist.linear.x = vx
    message.twist.twist.linear.y = vy
    message.twist.twist.linear.z = vz
    return message


def fresh_topic() -> str:
    return f"/test_odom_{uuid.uuid4().hex[:8]}"


def configured_moving(ros: Ros, topic: str) -> Moving:
    params: MovingParams = parse_params(Moving.Params, {"odom_topic": topic}, "measurement_server.moving")
    moving = Moving(FakeContext(name="moving", node=ros.node), params)
    moving.on_configure()
    return moving


@pytest.mark.parametrize(
    "publisher_reliability",
    [ReliabilityPolicy.RELIABLE, ReliabilityPolicy.BEST_EFFORT],
    ids=["reliable-publisher", "best-effort-publisher"],
)
def test_moving_follows_published_odometry(ros: Ros, publisher_reliability: ReliabilityPolicy) -> None:
    topic = fresh_topic()
    moving = configured_moving(ros, topic)
    publisher = ros.node.create_publisher(Odometry, topic, QoSProfile(depth=10, reliability=publisher_reliability))
    try:
        assert ros.spin_until(lambda: publisher.get_subscription_count() >= 1), "subscription never matched"
        assert moving.evaluate(None) is False, "starts inactive"

        assert ros.spin_until(lambda: moving.evaluate(None), lambda: publisher.publish(odometry(0.3, 0.3)))
        sent_slow = 0

        def publish_slow() -> None:
            nonlocal sent_slow
            sent_slow += 1
            publisher.publish(odometry(0.05))

        assert ros.spin_until(lambda: not moving.evaluate(None), publish_slow)
        # The counter is at +5 or more once active: at least 10 slow messages to reach -5.
        assert sent_slow >= 10
    finally:
        moving.on_cleanup()
        ros.node.destroy_publisher(publisher)


def test_cleanup_destroys_the_subscription_and_reconfigure_starts_inactive(ros: Ros) -> None:
    topic = fresh_topic()
    moving = configured_moving(ros, topic)
    publisher = ros.node.create_publisher(Odometry, topic, 10)
    try:
        assert ros.spin_until(lambda: publisher.get_subscription_count() >= 1)
        assert ros.spin_until(lambda: moving.evaluate(None), lambda: publisher.publish(odometry(1.0)))
        moving.on_cleanup()
        assert ros.spin_until(lambda: publisher.get_subscription_count() == 0), "subscription left behind"
        assert moving.evaluate(None) is False

        moving.on_configure()
        assert moving.evaluate(None) is False, "a new configuration starts inactive"
        moving.on_configure()
        assert len(list(ros.node.subscriptions)) == 1, "configure twice must not subscribe twice"
        assert ros.spin_until(lambda: moving.evaluate(None), lambda: publisher.publish(odometry(1.0)))
    finally:
        moving.on_cleanup()
        ros.node.destroy_publisher(publisher)


@pytest.mark.parametrize(
    ("message", "speed"),
    [
        pytest.param(odometry(3.0, 4.0), 5.0, id="planar"),
        pytest.param(odometry(-0.3), 0.3, id="reversing-counts-as-moving"),
        pytest.param(odometry(0.0, 0.0, 0.5), 0.5, id="vertical"),
        pytest.param(odometry(0.0), 0.0, id="still"),
    ],
)
def test_linear_speed(message: Odometry, speed: float) -> None:
    assert linear_speed(message) == pytest.approx(speed)
