"""What the tests of the robot measurements share: a node with its executor, and robot messages."""

from __future__ import annotations

import math
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import rclpy
from geometry_msgs.msg import TransformStamped, Twist
from nav_msgs.msg import Odometry
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from tf2_msgs.msg import TFMessage

from dc_core.measurement import Measurement
from dc_core.testing import PluginHarness

DEADLINE_S = 10.0


@dataclass
class Ros:
    node: Node
    executor: SingleThreadedExecutor
    harness: PluginHarness

    def spin_until(self, done: Callable[[], bool], step: Callable[[], None] = lambda: None) -> bool:
        """Spin (running ``step`` each turn) until ``done`` or the deadline."""
        deadline = time.monotonic() + DEADLINE_S
        while time.monotonic() < deadline:
            if done():
                return True
            step()
            self.executor.spin_once(timeout_sec=0.02)
        return done()

    def publisher(self, msg_type: Any, topic: str, qos: Any, subscribers: int = 1) -> Any:
        """A publisher, once it is matched with ``subscribers`` subscriptions."""
        publisher = self.node.create_publisher(msg_type, topic, qos)
        assert self.spin_until(lambda: publisher.get_subscription_count() >= subscribers), f"{topic} not matched"
        return publisher

    def start(self, cls: type[Measurement[Any]], params: dict[str, Any]) -> Any:
        return self.harness.start(cls, params)


@contextmanager
def ros_session(name: str, *, use_sim_time: bool = False, domain_id: int | None = None) -> Iterator[Ros]:
    """A node in a fresh context (in ``domain_id``, else the session's domain; following /clock with
    ``use_sim_time``), its executor, and a plugin harness on it."""
    context = Context()
    rclpy.init(context=context, domain_id=domain_id)
    try:
        node = rclpy.create_node(
            f"test_{name}_{uuid.uuid4().hex[:8]}",
            context=context,
            parameter_overrides=[Parameter("use_sim_time", Parameter.Type.BOOL, use_sim_time)],
        )
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        try:
            yield Ros(node, executor, PluginHarness(node))
        finally:
            executor.shutdown()
            node.destroy_node()
    finally:
        rclpy.shutdown(context=context)


@contextmanager
def odom_log(domain_id: int, qos: Any) -> Iterator[list[tuple[int, int]]]:
    """A bare subscriber of /odom spun on its own thread: (receive time ns, header stamp ns) of each message,
    what a process that only listens gets (the e2e recorder tests compare incident files with it)."""
    received: list[tuple[int, int]] = []

    def log(message: Any) -> None:
        stamp = message.header.stamp
        received.append((time.time_ns(), int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)))

    with ros_session("bare_odom_log", domain_id=domain_id) as ros:
        ros.node.create_subscription(Odometry, "/odom", log, qos)
        spinning = threading.Thread(target=ros.executor.spin, daemon=True)
        spinning.start()
        try:
            yield received
        finally:
            ros.executor.shutdown()
            spinning.join(5)


def unique(prefix: str) -> str:
    """A topic or frame name no other test uses (transient-local data of earlier tests stays around)."""
    return f"{prefix}_{uuid.uuid4().hex[:8]}"


def twist(vx: float = 0.0, vy: float = 0.0, wz: float = 0.0) -> Twist:
    message = Twist()
    message.linear.x, message.linear.y, message.angular.z = vx, vy, wz
    return message


def odometry(x: float, y: float, yaw: float, vx: float = 0.0, wz: float = 0.0, stamp_ns: int = 0) -> Odometry:
    message = Odometry()
    message.header.stamp.sec, message.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    message.header.frame_id, message.child_frame_id = "odom", "base_link"
    message.pose.pose.position.x, message.pose.pose.position.y = x, y
    message.pose.pose.orientation.z, message.pose.pose.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
    message.twist.twist.linear.x, message.twist.twist.angular.z = vx, wz
    return message


def transform(parent: str, child: str, x: float, y: float, yaw: float, stamp_ns: int = 0) -> TransformStamped:
    message = TransformStamped()
    message.header.stamp.sec, message.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    message.header.frame_id, message.child_frame_id = parent, child
    message.transform.translation.x, message.transform.translation.y = x, y
    message.transform.rotation.z, message.transform.rotation.w = math.sin(yaw / 2), math.cos(yaw / 2)
    return message


def tf_message(*transforms: TransformStamped) -> TFMessage:
    message = TFMessage()
    message.transforms = list(transforms)
    return message
