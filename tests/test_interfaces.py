"""dc_interfaces: the message contract, and a real publish/subscribe through rclpy.

The field names and types of StringStamped are the interop contract with the original C++ DC and
with any ROS 2 node that feeds DC; a change here breaks them.
"""

from __future__ import annotations

import time
from typing import Any

import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor

from dc_interfaces.msg import Condition, Heartbeat, StringStamped
from tests.domains import fresh_domain_id

TIMEOUT_S = 10.0


@pytest.mark.parametrize(
    ("message_type", "expected"),
    [
        (StringStamped, {"header": "std_msgs/Header", "data": "string", "group_key": "string"}),
        (Condition, {"data": "boolean"}),
        (
            Heartbeat,
            {
                "stamp": "builtin_interfaces/Time",
                "node_name": "string",
                "sequence": "uint64",
                "state": "uint8",
            },
        ),
    ],
    ids=["StringStamped", "Condition", "Heartbeat"],
)
def test_message_fields(message_type: Any, expected: dict[str, str]) -> None:
    # Order matters too: it is the serialization order on the wire.
    assert list(message_type.get_fields_and_field_types().items()) == list(expected.items())


def test_message_defaults_and_ranges() -> None:
    heartbeat = Heartbeat()
    assert (heartbeat.node_name, heartbeat.sequence, heartbeat.state) == ("", 0, 0)
    # Field checks are off by default in Jazzy (ROS_PYTHON_CHECK_FIELDS); ask for them.
    heartbeat = Heartbeat(check_fields=True)
    heartbeat.sequence = 2**64 - 1
    heartbeat.state = 255
    with pytest.raises(AssertionError):
        heartbeat.state = 256
    assert Condition().data is False
    assert Condition(data=True).data is True


def test_string_stamped_roundtrip() -> None:
    context = Context()
    rclpy.init(context=context, domain_id=fresh_domain_id())
    try:
        node = rclpy.create_node("dc_interfaces_roundtrip", context=context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        try:
            qos = 10  # KEEP_LAST 10, reliable, volatile
            received: list[StringStamped] = []
            node.create_subscription(StringStamped, "dc_test/string_stamped", received.append, qos)
            publisher = node.create_publisher(StringStamped, "dc_test/string_stamped", qos)

            deadline = time.monotonic() + TIMEOUT_S
            while publisher.get_subscription_count() < 1:
                assert time.monotonic() < deadline, "subscription never matched the publisher"
                executor.spin_once(timeout_sec=0.05)

            sent = StringStamped()
            sent.header.stamp.sec = 1_700_000_000
            sent.header.stamp.nanosec = 123_456_789
            sent.header.frame_id = "base_link"
            sent.data = '{"uptime": 42, "name": "caf\\u00e9 ✓"}'
            sent.group_key = "robot_group"
            publisher.publish(sent)

            while not received:
                assert time.monotonic() < deadline, "message not received before the deadline"
                executor.spin_once(timeout_sec=0.05)

            assert received == [sent]
            got = received[0]
            assert (got.header.stamp.sec, got.header.stamp.nanosec) == (1_700_000_000, 123_456_789)
            assert got.header.frame_id == "base_link"
            assert got.data == sent.data
            assert got.group_key == "robot_group"
        finally:
            executor.shutdown()
            node.destroy_node()
    finally:
        rclpy.shutdown(context=context)


# tf2_msgs/msg/TFMessage's hash as Jazzy's tf2_msgs gives it (`ros2 topic info -v /tf` on a robot): when
# make install builds DC's copy, a different hash would make DC's /tf subscriptions miss real robots.
UPSTREAM_TF_MESSAGE_HASH = "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"


def test_tf_message_has_the_type_hash_of_real_robots() -> None:
    from tf2_msgs.msg import TFMessage

    context = Context()
    rclpy.init(context=context, domain_id=fresh_domain_id())
    try:
        node = rclpy.create_node("dc_test_tf_hash", context=context)
        node.create_publisher(TFMessage, "/dc_test_tf_hash", 10)
        (endpoint,) = node.get_publishers_info_by_topic("/dc_test_tf_hash")
        assert str(endpoint.topic_type_hash) == UPSTREAM_TF_MESSAGE_HASH
        assert list(TFMessage.get_fields_and_field_types().items()) == [
            ("transforms", "sequence<geometry_msgs/TransformStamped>")
        ]
        node.destroy_node()
    finally:
        rclpy.shutdown(context=context)


def test_manage_lifecycle_nodes_is_nav2s_service() -> None:
    from dc_interfaces.srv import ManageLifecycleNodes

    request = ManageLifecycleNodes.Request
    assert (request.STARTUP, request.PAUSE, request.RESUME, request.RESET, request.SHUTDOWN) == (0, 1, 2, 3, 4)
    assert request.get_fields_and_field_types() == {"command": "uint8"}
    assert ManageLifecycleNodes.Response.get_fields_and_field_types() == {"success": "boolean"}
