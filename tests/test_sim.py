"""dc_sim: the simulated robot's kinematics, warehouse and ROS interface.

The pure tests check the motion against closed forms (a circle closes, a route's path length is the
sum of its segments) and the warehouse against the properties a map writer's tests rely on. The ROS
tests run the simulator as ``python -m dc_sim`` (its CLI, its exit) or in this process under its
own context and executor, and observe it from another context, as DC would from another process.
"""

from __future__ import annotations

import itertools
import json
import math
import os
import signal
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
import rclpy
from geometry_msgs.msg import Twist
from nav_msgs.msg import OccupancyGrid, Odometry
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from tf2_msgs.msg import TFMessage

from dc_sim.kinematics import DiffDrive, Pose2D, RouteFollower, Waypoint, wrap_angle
from dc_sim.node import CLOCK_EPOCH_NS, SimOptions, SimRobot, parse_args
from dc_sim.warehouse import OCCUPIED, UNKNOWN, warehouse_grid, warehouse_route, warehouse_start
from tests.ros_util import two_contexts, wait_for

REPOSITORY = Path(__file__).resolve().parent.parent
NS = 1_000_000_000
BEST_EFFORT = QoSProfile(depth=50, reliability=ReliabilityPolicy.BEST_EFFORT)
RELIABLE = QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


def close(actual: Sequence[float], expected: Sequence[float], tolerance: float = 1e-9) -> bool:
    return len(actual) == len(expected) and all(
        math.isclose(a, e, rel_tol=tolerance, abs_tol=tolerance) for a, e in zip(actual, expected, strict=True)
    )


# -- kinematics --------------------------------------------------------------------------------


def test_wrap_angle_is_half_open() -> None:
    assert wrap_angle(-math.pi) == math.pi
    assert wrap_angle(3 * math.pi) == pytest.approx(math.pi)
    assert wrap_angle(-0.5 * math.pi - 2 * math.tau) == pytest.approx(-0.5 * math.pi)


def test_diff_drive_straight_line() -> None:
    base = DiffDrive(Pose2D(1.0, 2.0, math.pi / 2))
    for _ in range(100):
        base.step(0.5, 0.0, 0.02)
    assert base.pose.x == pytest.approx(1.0, abs=1e-12)
    assert base.pose.y == pytest.approx(3.0)
    assert base.pose.yaw == pytest.approx(math.pi / 2)
    assert base.distance == pytest.approx(1.0)
    for _ in range(50):
        base.step(-0.5, 0.0, 0.02)  # backwards: the path still lengthens
    assert base.pose.y == pytest.approx(2.5)
    assert base.distance == pytest.approx(1.5)


def test_diff_drive_full_circle_closes() -> None:
    # v = 0.5 m/s, w = 0.5 rad/s: a circle of radius v / w = 1 m, once round in 2*pi / w = 4*pi s,
    # so a path of length v * 4*pi = 2*pi m, the circumference.
    steps = 1000
    dt = math.tau / 0.5 / steps
    base = DiffDrive()
    for step in range(steps):
        base.step(0.5, 0.5, dt)
        if step == steps // 2 - 1:
            # Half way round, counter-clockwise from heading +x: the top of the circle, heading -x.
            assert close((base.pose.x, base.pose.y), (0.0, 2.0))
            assert abs(base.pose.yaw) == pytest.approx(math.pi)
    assert base.pose.x == pytest.approx(0.0, abs=1e-9)
    assert base.pose.y == pytest.approx(0.0, abs=1e-9)
    assert base.pose.yaw == pytest.approx(0.0, abs=1e-9)
    assert base.distance == pytest.approx(math.tau * 1.0)


def test_pose_compose() -> None:
    composed = Pose2D(1.0, 0.0, math.pi / 2).compose(Pose2D(1.0, 0.0, math.pi / 2))
    assert close((composed.x, composed.y, composed.yaw), (1.0, 1.0, math.pi))


@dataclass
class RouteRun:
    arrivals: list[int] = field(default_factory=list)  # waypoint indices in the order stopped at
    stopped_steps: dict[int, int] = field(default_factory=dict)
    poses: list[Pose2D] = field(default_factory=list)
    distance: float = 0.0
    steps: int = 0


def run_route(follower: RouteFollower, start: Pose2D, dt: float, max_steps: int) -> RouteRun:
    base = DiffDrive(start)
    run = RouteRun()
    while not follower.finished and run.steps < max_steps:
        base.step(*follower.command(base.pose, dt), dt)
        run.steps += 1
        run.poses.append(base.pose)
        if follower.stopped_at is not None:
            run.stopped_steps[follower.stopped_at] = run.stopped_steps.get(follower.stopped_at, 0) + 1
            if not run.arrivals or run.arrivals[-1] != follower.stopped_at:
                run.arrivals.append(follower.stopped_at)
    run.distance = base.distance
    return run


def test_route_follower_visits_every_waypoint_in_order() -> None:
    route, start, dt = warehouse_route(), warehouse_start(), 0.02
    follower = RouteFollower(route)
    run = run_route(follower, start, dt, max_steps=100_000)

    assert follower.finished
    assert run.arrivals == list(range(len(route)))
    for index, waypoint in enumerate(route):
        assert run.stopped_steps[index] * dt == pytest.approx(waypoint.stop_s, abs=dt)
    corners = [(start.x, start.y), *((w.x, w.y) for w in route)]
    segments = sum(math.dist(a, b) for a, b in itertools.pairwise(corners))
    assert run.distance == pytest.approx(segments, rel=0.03)
    grid = warehouse_grid()
    assert all(grid.value_at(pose.x, pose.y) == 0 for pose in run.poses), "the robot drove through an obstacle"
    # Finished, it stays put.
    assert follower.command(run.poses[-1], dt) == (0.0, 0.0)


def test_route_follower_loops() -> None:
    route = [Waypoint(1.0, 0.0, 0.1), Waypoint(1.0, 1.0, 0.1)]
    follower = RouteFollower(route, loop=True)
    run = run_route(follower, Pose2D(), 0.02, max_steps=3000)
    assert not follower.finished
    assert run.arrivals[:5] == [0, 1, 0, 1, 0]


def test_route_follower_realigns_after_being_pushed() -> None:
    follower = RouteFollower([Waypoint(2.0, 0.0, 0.0)])
    assert follower.command(Pose2D(), 0.02)[0] > 0.0  # facing it: drives
    v, w = follower.command(Pose2D(0.5, 0.0, math.pi), 0.02)  # turned away (as by teleop): turns in place
    assert v == 0.0
    assert abs(w) == pytest.approx(1.0)


# -- warehouse -----------------------------------------------------------------------------------


def test_warehouse_grid() -> None:
    grid = warehouse_grid()
    assert grid.width != grid.height
    assert (grid.width, grid.height, grid.resolution) == (200, 120, 0.05)
    assert len(grid.data) == grid.width * grid.height
    values = set(grid.data)
    assert {UNKNOWN, 0, OCCUPIED} <= values
    assert values & set(range(1, OCCUPIED)), "no intermediate occupancy"
    assert values <= set(range(-1, OCCUPIED + 1))
    # Row-major from the bottom row: the bottom-left cell is the corner of the walls, the right
    # columns are the unknown band, the cell at the start is free.
    assert grid.data[0] == OCCUPIED
    assert grid.data[grid.width - 1] == UNKNOWN
    start = warehouse_start()
    assert grid.value_at(start.x, start.y) == 0
    assert grid.value_at(-0.95, 2.0) == OCCUPIED  # west wall
    assert grid.value_at(3.5, 1.0) == OCCUPIED  # first shelf row


def test_warehouse_route_is_reachable() -> None:
    grid, route = warehouse_grid(), warehouse_route()
    assert 4 <= len(route) <= 6
    assert all(2.0 <= waypoint.stop_s <= 4.0 for waypoint in route)
    assert all(grid.value_at(waypoint.x, waypoint.y) == 0 for waypoint in route)
    # Straight segments (the loop's closing one included) keep 0.2 m clear of anything not free.
    start = warehouse_start()
    corners = [(start.x, start.y), *((w.x, w.y) for w in [*route, route[0]])]
    clearance = 0.2
    for a, b in itertools.pairwise(corners):
        samples = int(math.dist(a, b) / 0.02) + 1
        for i in range(samples + 1):
            x, y = a[0] + (b[0] - a[0]) * i / samples, a[1] + (b[1] - a[1]) * i / samples
            for dx, dy in ((0, 0), (clearance, 0), (-clearance, 0), (0, clearance), (0, -clearance)):
                assert grid.value_at(x + dx, y + dy) == 0, f"segment {a} -> {b} blocked near ({x:.2f}, {y:.2f})"


def test_parse_args() -> None:
    options = parse_args(["--clock", "--rate", "4", "--duration", "10", "--truth", "t.jsonl", "--odom-qos", "reliable"])
    assert options == SimOptions(
        rate=4.0, clock=True, duration=10.0, odom_qos="reliable", truth=Path("t.jsonl"), wait_subscribers=0.0
    )
    with pytest.raises(SystemExit):
        parse_args(["--rate", "0"])


# -- ROS ---------------------------------------------------------------------------------------


def stamp_ns(stamp: Any) -> int:
    return int(stamp.sec) * NS + int(stamp.nanosec)


def yaw_of(q: Any) -> float:
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


@dataclass
class Observer:
    """A node in its own context recording what the simulator publishes."""

    node: Any
    executor: SingleThreadedExecutor
    odom: list[Any] = field(default_factory=list)
    tf: list[Any] = field(default_factory=list)
    tf_static: list[Any] = field(default_factory=list)
    maps: list[Any] = field(default_factory=list)
    cmd_vel: list[Any] = field(default_factory=list)
    clock: list[tuple[float, int]] = field(default_factory=list)  # (wall monotonic s, clock ns)

    def spin(self) -> None:
        self.executor.spin_once(timeout_sec=0.02)

    def until(self, condition: Any, deadline_s: float = 20.0) -> bool:
        return wait_for(condition, self.spin, deadline_s)

    def subscribe(self, namespace: str = "") -> None:
        node = self.node
        node.create_subscription(Odometry, f"{namespace}/odom", self.odom.append, BEST_EFFORT)
        node.create_subscription(TFMessage, "/tf", self.tf.append, RELIABLE)
        node.create_subscription(TFMessage, "/tf_static", self.tf_static.append, LATCHED)
        node.create_subscription(Twist, f"{namespace}/cmd_vel", self.cmd_vel.append, BEST_EFFORT)
        node.create_subscription(
            Clock, f"{namespace}/clock", lambda m: self.clock.append((time.monotonic(), stamp_ns(m.clock))), RELIABLE
        )

    def subscribe_map(self, namespace: str = "") -> None:
        self.node.create_subscription(OccupancyGrid, f"{namespace}/map", self.maps.append, LATCHED)


@pytest.fixture
def observer() -> Iterator[Observer]:
    context = Context()
    rclpy.init(context=context)
    node = Node(f"sim_observer_{uuid.uuid4().hex[:8]}", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        yield Observer(node, executor)
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=context)


def read_truth(path: Path) -> list[dict[str, Any]]:
    if not path.exists():
        return []
    text = path.read_text()
    return [json.loads(line) for line in text[: text.rfind("\n") + 1].splitlines()]


def start_sim(tmp_path: Path, *args: str) -> subprocess.Popen[bytes]:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPOSITORY), os.environ.get("PYTHONPATH")]))}
    return subprocess.Popen(
        [sys.executable, "-m", "dc_sim", *args],
        cwd=REPOSITORY,
        env=env,
        stdout=(tmp_path / "sim.out").open("wb"),
        stderr=subprocess.STDOUT,
    )


def stop(process: subprocess.Popen[bytes]) -> None:
    if process.poll() is None:
        process.kill()
        process.wait()


def test_sim_process_publishes_the_truth(tmp_path: Path, observer: Observer) -> None:
    truth = tmp_path / "truth.jsonl"
    observer.subscribe()
    # The simulator waits for our odom subscription, so nothing it publishes while moving is missed.
    sim = start_sim(
        tmp_path, "--clock", "--rate", "4", "--duration", "12", "--truth", str(truth), "--wait-subscribers", "30"
    )
    try:
        assert observer.until(lambda: len(observer.odom) >= 5), (tmp_path / "sim.out").read_text()
        observer.subscribe_map()  # late: the latched map must still arrive
        assert observer.until(lambda: sim.poll() is not None, deadline_s=30.0), "the sim did not stop after --duration"
        assert sim.returncode == 0, (tmp_path / "sim.out").read_text()
        assert observer.until(lambda: bool(observer.maps))
    finally:
        stop(sim)

    grid = observer.maps[0]
    expected = warehouse_grid()
    assert (grid.info.width, grid.info.height) == (expected.width, expected.height)
    assert grid.info.resolution == pytest.approx(expected.resolution)
    assert grid.header.frame_id == "map"
    assert list(grid.data) == expected.data

    statics = {(t.header.frame_id, t.child_frame_id) for m in observer.tf_static for t in m.transforms}
    assert len(observer.tf_static) == 1
    assert statics == {("base_link", "base_scan"), ("base_link", "camera_link")}

    lines = read_truth(truth)
    assert lines, "no truth written"
    assert lines[-1]["t"] == pytest.approx(CLOCK_EPOCH_NS / NS + 12.0)
    assert lines[-1]["distance"] > 1.0
    spacing = (lines[-1]["t"] - lines[0]["t"]) / (len(lines) - 1)
    assert spacing == pytest.approx(0.1, abs=0.02)
    by_ms = {round(line["t"] * 1000): line for line in lines}

    matched = 0
    for odometry in observer.odom:
        assert (odometry.header.frame_id, odometry.child_frame_id) == ("odom", "base_link")
        line = by_ms.get(round(stamp_ns(odometry.header.stamp) / 1e6))
        if line is None:
            continue
        matched += 1
        pose = odometry.pose.pose
        assert close((pose.position.x, pose.position.y), (line["odom"]["x"], line["odom"]["y"]))
        assert yaw_of(pose.orientation) == pytest.approx(line["odom"]["yaw"], abs=1e-9)
        assert odometry.twist.twist.linear.x == pytest.approx(line["v"])
        assert odometry.twist.twist.angular.z == pytest.approx(line["w"])
    assert matched >= 20

    # /tf carries the same odometry with the same stamps, and map -> odom composes to the truth's map pose.
    odom_by_stamp = {stamp_ns(o.header.stamp): o for o in observer.odom}
    for message in observer.tf[-20:]:
        transforms = {(t.header.frame_id, t.child_frame_id): t for t in message.transforms}
        assert set(transforms) == {("odom", "base_link"), ("map", "odom")}
        base = transforms[("odom", "base_link")]
        stamp = stamp_ns(base.header.stamp)
        assert stamp == stamp_ns(transforms[("map", "odom")].header.stamp)
        map_to_odom = transforms[("map", "odom")].transform
        odom_pose = Pose2D(base.transform.translation.x, base.transform.translation.y, yaw_of(base.transform.rotation))
        map_pose = Pose2D(map_to_odom.translation.x, map_to_odom.translation.y, yaw_of(map_to_odom.rotation)).compose(
            odom_pose
        )
        if stamp in odom_by_stamp:
            assert odom_pose.x == pytest.approx(odom_by_stamp[stamp].pose.pose.position.x)
        line = by_ms.get(round(stamp / 1e6))
        if line is not None:
            assert close((map_pose.x, map_pose.y), (line["map"]["x"], line["map"]["y"]))

    # The route's commands are on cmd_vel for observers.
    assert any(twist.linear.x > 0.1 for twist in observer.cmd_vel)

    # Simulated time ran about 4 times as fast as the wall clock.
    moving = [(wall, clock) for wall, clock in observer.clock if clock > CLOCK_EPOCH_NS]
    (wall_0, clock_0), (wall_1, clock_1) = moving[0], moving[-1]
    assert wall_1 - wall_0 > 1.5
    assert (clock_1 - clock_0) / NS / (wall_1 - wall_0) == pytest.approx(4.0, rel=0.2)


def test_sim_process_stops_cleanly_on_sigterm(tmp_path: Path) -> None:
    truth = tmp_path / "truth.jsonl"
    sim = start_sim(tmp_path, "--loop", "--truth", str(truth))
    try:
        deadline = time.monotonic() + 20.0
        # The truth file growing is the sign it runs; polling a file has no event to wait on.
        while len(read_truth(truth)) < 3 and time.monotonic() < deadline and sim.poll() is None:
            time.sleep(0.05)
        assert len(read_truth(truth)) >= 3, (tmp_path / "sim.out").read_text()
        sim.send_signal(signal.SIGTERM)
        assert sim.wait(timeout=10.0) == 0, (tmp_path / "sim.out").read_text()
    finally:
        stop(sim)
    assert truth.read_text().endswith("\n")  # every line complete


@pytest.fixture
def sim_contexts() -> Iterator[tuple[Context, Context]]:
    with two_contexts() as contexts:
        yield contexts


def test_teleop_on_cmd_vel_takes_over_the_route(sim_contexts: tuple[Context, Context]) -> None:
    sim_context, observer_context = sim_contexts
    namespace = "robot_" + uuid.uuid4().hex[:6]
    sim = SimRobot(SimOptions(rate=4.0, clock=True, namespace=namespace), context=sim_context)
    sim_executor = SingleThreadedExecutor(context=sim_context)
    sim_executor.add_node(sim)
    stopping = threading.Event()

    def run_sim() -> None:
        while not stopping.is_set():
            sim_executor.spin_once(timeout_sec=0.05)

    thread = threading.Thread(target=run_sim, daemon=True)
    thread.start()
    node = Node("sim_teleop", context=observer_context)
    executor = SingleThreadedExecutor(context=observer_context)
    executor.add_node(node)
    observer = Observer(node, executor)
    try:
        observer.subscribe(f"/{namespace}")
        assert observer.until(lambda: any(t.linear.x > 0.1 for t in observer.cmd_vel)), "no route commands"
        assert observer.until(lambda: any(o.twist.twist.linear.x > 0.1 for o in observer.odom))

        teleop = node.create_publisher(Twist, f"/{namespace}/cmd_vel", 10)
        command = Twist()
        command.linear.x, command.angular.z = 0.2, -0.3

        def obeys() -> bool:
            teleop.publish(command)
            return close(sim.command, (0.2, -0.3))

        assert observer.until(obeys), f"the sim does not follow cmd_vel: {sim.command}"
        paused_at = sim.follower.target
        # Commands stop (the publisher stays): the watchdog stops the base.
        assert observer.until(lambda: sim.command == (0.0, 0.0)), "the watchdog did not stop the base"
        assert sim.follower.target == paused_at

        node.destroy_publisher(teleop)
        # The route resumes: the sim's own commands come back on cmd_vel, and the base moves again.
        assert observer.until(lambda: sim.command != (0.0, 0.0)), "the route did not resume"
    finally:
        stopping.set()
        thread.join(timeout=5.0)
        sim_executor.shutdown()
        sim.destroy_node()
        executor.shutdown()
        node.destroy_node()
