"""DistanceTraveled: the odometer's rules, and the measurement fed with real /tf and /odom messages."""

from __future__ import annotations

import itertools
import math
import random
from collections.abc import Iterator

import pytest
from nav_msgs.msg import Odometry
from rclpy.qos import QoSProfile, ReliabilityPolicy
from tf2_msgs.msg import TFMessage

from dc_measurements.distance_traveled import DistanceTraveled, Odometer
from tests.measurement_helpers import assert_valid
from tests.robot_helpers import Ros, odometry, ros_session, tf_message, transform, unique


def test_a_standing_robot_does_not_drift() -> None:
    odometer = Odometer(min_step=0.01)
    rng = random.Random(4)
    for _ in range(10_000):  # 3 mm of jitter around one spot
        odometer.add(1.0 + rng.uniform(-0.003, 0.003), 2.0 + rng.uniform(-0.003, 0.003))
    assert odometer.total == 0.0


def test_slow_motion_below_the_minimum_step_still_adds_up() -> None:
    odometer = Odometer(min_step=0.01)
    for i in range(1001):  # 1 mm per sample along x: every sample is below min_step
        odometer.add(i * 0.001, 0.0)
    assert odometer.total == pytest.approx(1.0, abs=0.01)


def test_the_total_is_cumulative_along_a_square() -> None:
    odometer = Odometer(min_step=0.01)
    corners = [(0.0, 0.0), (1.0, 0.0), (1.0, 1.0), (0.0, 1.0), (0.0, 0.0)]
    for (x0, y0), (x1, y1) in itertools.pairwise(corners):
        for i in range(1, 21):
            odometer.add(x0 + (x1 - x0) * i / 20, y0 + (y1 - y0) * i / 20)
    assert odometer.total == pytest.approx(4.0 - 0.05)  # the first sample is the start, at the first corner + 5 cm


def test_a_jump_longer_than_max_step_is_not_travel() -> None:
    odometer = Odometer(min_step=0.01, max_step=0.5)
    for x in (0.0, 0.1, 0.2, 5.2, 5.3):
        odometer.add(x, 0.0)
    assert odometer.total == pytest.approx(0.3)
    assert odometer.jumps == 1


@pytest.fixture
def ros() -> Iterator[Ros]:
    with ros_session("distance") as session:
        yield session


def test_distance_from_tf_counts_every_update_not_only_polls(ros: Ros) -> None:
    odom, base = unique("odom"), unique("base")
    plugin = ros.start(DistanceTraveled, {"global_frame": odom, "robot_base_frame": base})
    assert plugin.collect() == {"distance_traveled": 0.0}
    publisher = ros.publisher(TFMessage, "/tf", QoSProfile(depth=100))
    # A circle of radius 1 m in 100 steps: its length is 2*pi*sin(pi/100)*100 ≈ 6.282 m; between polls the
    # robot comes back to where it started, so a distance taken at polls would be 0.
    for i in range(101):
        angle = 2 * math.pi * i / 100
        publisher.publish(tf_message(transform(odom, base, math.cos(angle), math.sin(angle), angle, (i + 1) * 10**8)))
        ros.executor.spin_once(timeout_sec=0)
    expected = 200 * math.sin(math.pi / 100)
    assert ros.spin_until(lambda: plugin.collect()["distance_traveled"] >= expected - 1e-9)
    record = plugin.collect()
    assert_valid(DistanceTraveled, record)
    assert record["distance_traveled"] == pytest.approx(expected)
    ros.harness.stop(plugin)


def test_distance_from_odometry_restarts_its_path_when_time_jumps_back(ros: Ros) -> None:
    topic = unique("/odom")
    plugin = ros.start(DistanceTraveled, {"source": "odom", "odom_topic": topic})
    publisher = ros.publisher(Odometry, topic, QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT))
    for i in range(11):  # 1 m along x, from t = 20 s
        publisher.publish(odometry(i * 0.1, 0.0, 0.0, stamp_ns=(200 + i) * 10**8))
        ros.executor.spin_once(timeout_sec=0)
    assert ros.spin_until(lambda: plugin.collect()["distance_traveled"] >= 1.0 - 1e-9)
    # The bag starts over (t = 10 s): the robot is back at 0 at an earlier time. Not a 1 m move.
    for i in range(6):
        publisher.publish(odometry(i * 0.1, 0.0, 0.0, stamp_ns=(100 + i) * 10**8))
        ros.executor.spin_once(timeout_sec=0)
    assert ros.spin_until(lambda: plugin.collect()["distance_traveled"] >= 1.5 - 1e-9)
    assert plugin.collect()["distance_traveled"] == pytest.approx(1.5)
    ros.harness.stop(plugin)


def test_the_same_frame_twice_is_refused_at_configure() -> None:
    from dc_core.errors import PluginError
    from dc_core.testing import PluginHarness

    with pytest.raises(PluginError, match="both 'map'"):
        PluginHarness().start(DistanceTraveled, {"global_frame": "map", "robot_base_frame": "/map"})
