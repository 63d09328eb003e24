"""The TF listener under the TF a real robot publishes: real /tf, /tf_static and /clock messages, in-process.

History is cleared only when the node's clock jumps back (as tf2_ros): stamps that go back across links
(AMCL post-dating map -> odom, odometry arriving late) or a transform dated in the future are normal.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator

import pytest
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.time import Time
from rosgraph_msgs.msg import Clock
from tf2_msgs.msg import TFMessage

from dc_core.tf import TransformBuffer, TransformError
from dc_measurements.distance_traveled import DistanceTraveled
from dc_measurements.position import Position
from tests.robot_helpers import Ros, ros_session, tf_message, transform, unique

NS = 1_000_000_000
STATIC_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
# Both plugins subscribe to /tf.
TF_SUBSCRIBERS = 2


@pytest.fixture
def ros() -> Iterator[Ros]:
    with ros_session("tf_listener") as session:
        yield session


@pytest.fixture
def sim_ros() -> Iterator[Ros]:
    with ros_session("tf_listener_sim", use_sim_time=True) as session:
        yield session


def newest(buffer: TransformBuffer, parent: str, child: str) -> int:
    """The newest stamp of one link (-1 while it is unknown)."""
    try:
        return buffer.latest_time(parent, child)
    except TransformError:
        return -1


def has(buffer: TransformBuffer, parent: str, child: str, stamp_ns: int) -> Callable[[], bool]:
    """A condition to spin for: the link holds a sample at ``stamp_ns`` or later."""
    return lambda: newest(buffer, parent, child) >= stamp_ns


def test_amcl_post_dating_map_to_odom_with_late_odometry_gives_a_map_position_every_poll(ros: Ros) -> None:
    """Nav2 with AMCL: map -> odom at 10 Hz post-dated by transform_tolerance (1 s), odom -> base_link at
    50 Hz stamped 50 ms late. Nothing here is time going back."""
    map_frame, odom, base = unique("map"), unique("odom"), unique("base_link")
    position = ros.start(Position, {"global_frame": map_frame, "robot_base_frame": base, "transform_timeout": 0.0})
    distance = ros.start(DistanceTraveled, {"global_frame": map_frame, "robot_base_frame": base})
    tf = ros.publisher(TFMessage, "/tf", QoSProfile(depth=100), subscribers=TF_SUBSCRIBERS)
    start_ns, speed, odom_late_ns, amcl_tolerance_ns = 1_000 * NS, 1.0, 50_000_000, NS
    # The robot drives along odom's x; odom is at (2, 1) in the map, turned a quarter turn.
    map_odom = (2.0, 1.0, math.pi / 2)
    polls: list[tuple[dict[str, float] | None, int | None]] = []
    first_pose_ns = last_pose_ns = 0
    for step in range(150):  # 3 s of the robot's time, one 20 ms odometry period per step
        now_ns = start_ns + step * 20_000_000
        odom_ns = now_ns - odom_late_ns
        tf.publish(tf_message(transform(odom, base, speed * (odom_ns - start_ns) / NS, 0.0, 0.0, odom_ns)))
        waits = [(odom, base, odom_ns)]
        if step % 5 == 0:
            tf.publish(tf_message(transform(map_frame, odom, *map_odom, now_ns + amcl_tolerance_ns)))
            waits.append((map_frame, odom, now_ns + amcl_tolerance_ns))
        for buffer in (position.buffer, distance.buffer):
            for parent, child, stamp in waits:
                assert ros.spin_until(has(buffer, parent, child, stamp)), (
                    f"{parent} -> {child} at {stamp} never arrived"
                )
        record, stamp, _ = position.collect_stamped()
        polls.append((record, stamp))
        if record is not None:
            first_pose_ns = first_pose_ns or odom_ns
            last_pose_ns = odom_ns
    # The first map pose needs map -> odom's history to reach back to the odometry's time: 1 s after the start.
    answered = [i for i, (record, _) in enumerate(polls) if record is not None]
    assert answered, f"no Position in {map_frame} in {len(polls)} polls (counters {position.counters()})"
    assert answered[0] <= 55
    assert answered == list(range(answered[0], len(polls))), "a poll after the first answered gave no position"
    for record, dated_ns in polls[answered[0] :]:
        assert record is not None and dated_ns is not None
        travelled = speed * (dated_ns - start_ns) / NS
        assert record["x"] == pytest.approx(map_odom[0]) and record["y"] == pytest.approx(map_odom[1] + travelled)
        assert record["yaw"] == pytest.approx(math.pi / 2)
    assert position.counters()["tf_time_jumps"] == 0 and position.counters()["tf_old_data"] == 0
    # One unbroken path from the first map pose to the last: a restart would lose a step, a clear many.
    assert distance.counters()["tf_time_jumps"] == 0
    assert distance.collect()["distance_traveled"] == pytest.approx(speed * (last_pose_ns - first_pose_ns) / NS)
    ros.harness.stop(position)
    ros.harness.stop(distance)


def clock(ros: Ros, publisher: object, at_ns: int) -> None:
    """Publish ``at_ns`` on /clock and wait until the node's clock shows it."""
    message = Clock()
    message.clock = Time(nanoseconds=at_ns).to_msg()
    publisher.publish(message)  # type: ignore[attr-defined]
    assert ros.spin_until(lambda: ros.node.get_clock().now().nanoseconds == at_ns), f"/clock {at_ns} not followed"


def test_a_bag_replayed_with_loop_clears_the_history_once_and_restarts_the_path(sim_ros: Ros) -> None:
    ros = sim_ros
    odom, base, laser = unique("odom"), unique("base_link"), unique("laser")
    static = ros.node.create_publisher(TFMessage, "/tf_static", STATIC_QOS)
    static.publish(tf_message(transform(base, laser, 0.2, 0.0, 0.0)))
    position = ros.start(Position, {"global_frame": odom, "robot_base_frame": laser, "transform_timeout": 0.0})
    distance = ros.start(DistanceTraveled, {"global_frame": odom, "robot_base_frame": base})
    clock_publisher = ros.publisher(Clock, "/clock", QoSProfile(depth=10))
    tf = ros.publisher(TFMessage, "/tf", QoSProfile(depth=100), subscribers=TF_SUBSCRIBERS)
    bag_start_ns = 100 * NS

    def play() -> None:
        """The bag: 1 m along x in 1 s, /clock before each message as `ros2 bag play` does."""
        for i in range(11):
            at_ns = bag_start_ns + i * NS // 10
            clock(ros, clock_publisher, at_ns)
            tf.publish(tf_message(transform(odom, base, i * 0.1, 0.0, 0.0, at_ns)))
            for buffer in (position.buffer, distance.buffer):
                assert ros.spin_until(has(buffer, odom, base, at_ns))

    play()
    assert ros.spin_until(lambda: position.collect() is not None)
    assert position.collect() == {"x": pytest.approx(1.2), "y": pytest.approx(0.0), "yaw": pytest.approx(0.0)}
    assert distance.collect()["distance_traveled"] == pytest.approx(1.0)
    assert position.counters()["tf_time_jumps"] == distance.counters()["tf_time_jumps"] == 0

    clock(ros, clock_publisher, bag_start_ns)  # --loop: the bag starts over, /clock goes back 1 s
    assert position.counters()["tf_time_jumps"] == distance.counters()["tf_time_jumps"] == 1
    assert position.collect() is None  # the moving link is forgotten...
    assert position.buffer.latest_time(base, laser) == 0  # ...the static one stays
    warnings = ros.harness.context(position).logger.at("warning")
    assert any("clock jumped back 1.0 s: transform history cleared" in line for line in warnings), warnings

    play()  # the second run: /clock and /tf go forward again, nothing more is cleared
    assert position.counters()["tf_time_jumps"] == distance.counters()["tf_time_jumps"] == 1
    record, stamp, _ = position.collect_stamped()
    assert record == {"x": pytest.approx(1.2), "y": pytest.approx(0.0), "yaw": pytest.approx(0.0)}
    assert stamp == bag_start_ns + NS
    # 1 m per run; the way back from the end of the first run to the start of the second is no travel.
    assert distance.collect()["distance_traveled"] == pytest.approx(2.0)
    ros.harness.stop(position)
    ros.harness.stop(distance)


def test_a_transform_dated_in_the_future_is_kept_and_used(ros: Ros) -> None:
    map_frame, base, odom, wheel = unique("map"), unique("base_link"), unique("odom"), unique("wheel")
    position = ros.start(Position, {"global_frame": map_frame, "robot_base_frame": base, "transform_timeout": 0.0})
    tf = ros.publisher(TFMessage, "/tf", QoSProfile(depth=100))
    now_ns, future_ns = 1_000 * NS, 1_030 * NS
    tf.publish(tf_message(transform(map_frame, base, 3.0, 4.0, 0.5, future_ns)))
    assert ros.spin_until(lambda: newest(position.buffer, map_frame, base) == future_ns)
    # Other links go on at the present time, 30 s before it.
    for i in range(20):
        at_ns = now_ns + i * NS // 10
        tf.publish(tf_message(transform(odom, wheel, 0.1 * i, 0.0, 0.0, at_ns)))
        assert ros.spin_until(has(position.buffer, odom, wheel, at_ns))
    record, stamp, _ = position.collect_stamped()
    assert record == {"x": pytest.approx(3.0), "y": pytest.approx(4.0), "yaw": pytest.approx(0.5)}
    assert stamp == future_ns
    assert position.counters()["tf_time_jumps"] == position.counters()["tf_old_data"] == 0
    ros.harness.stop(position)


def test_stamps_going_back_without_the_clock_keep_the_history_and_count_what_is_ignored(ros: Ros) -> None:
    """A bag looped without use_sim_time: the node's clock never went back, so nothing is cleared (as
    tf2_ros); samples older than their link's 10 s history are ignored, counted and logged, never silently."""
    odom, base = unique("odom"), unique("base_link")
    position = ros.start(Position, {"global_frame": odom, "robot_base_frame": base, "transform_timeout": 0.0})
    tf = ros.publisher(TFMessage, "/tf", QoSProfile(depth=100))
    tf.publish(tf_message(transform(odom, base, 1.0, 0.0, 0.0, 130 * NS)))
    assert ros.spin_until(lambda: newest(position.buffer, odom, base) == 130 * NS)
    tf.publish(tf_message(transform(odom, base, 0.0, 0.0, 0.0, 100 * NS)))
    assert ros.spin_until(lambda: position.counters()["tf_old_data"] == 1)
    assert position.collect() == {"x": pytest.approx(1.0), "y": pytest.approx(0.0), "yaw": pytest.approx(0.0)}
    assert position.counters()["tf_time_jumps"] == 0
    warnings = ros.harness.context(position).logger.at("warning")
    assert any("older than what the link holds" in line and "use_sim_time" in line for line in warnings), warnings
    ros.harness.stop(position)
