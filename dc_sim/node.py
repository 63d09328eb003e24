"""The simulated robot as a ROS 2 node: what a robot's drivers, localiser and map server publish.

One fixed simulation step runs per tick of a 50 Hz wall-clock timer and advances simulated time by
``0.02 * rate`` seconds: the base integrates a (v, w) command, then the step publishes ``odom``
(nav_msgs/Odometry), ``/tf`` (odom -> base_link and a constant map -> odom, as a localiser would)
and, with ``--clock``, ``clock`` carrying the simulated time, so that a DC started with
``use_sim_time`` follows the simulator and ``--rate 4`` runs it four times faster than real time.
``/tf_static`` (the sensors' mounts) and ``map`` (the warehouse grid) are latched at start.

The command comes from a :class:`~dc_sim.kinematics.RouteFollower` on the warehouse route, and is
published on ``cmd_vel`` so that observers see what drives the base, as they would see Nav2's. When
another node publishes on ``cmd_vel`` (teleoperation, a test) the route pauses and the base obeys it
instead, with a watchdog that stops the base when the commands stop coming.

``--truth`` writes the ground truth (exact pose, path length, command, waypoint) as JSON lines
stamped with the clock of the published headers, so that DC's measurements can be compared with it.
"""

from __future__ import annotations

import argparse
import json
import math
import signal
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import IO, Any

import rclpy
from builtin_interfaces.msg import Time
from geometry_msgs.msg import TransformStamped, Twist
from nav_msgs.msg import OccupancyGrid, Odometry
from rclpy.clock import Clock
from rclpy.clock_type import ClockType
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from rosgraph_msgs.msg import Clock as ClockMessage
from sensor_msgs.msg import Image
from tf2_msgs.msg import TFMessage

from dc_core.signals import StopRequest
from dc_sim.camera import CameraView
from dc_sim.kinematics import DiffDrive, Pose2D, RouteFollower
from dc_sim.warehouse import Grid, warehouse_grid, warehouse_route, warehouse_start

STEP_S = 0.02  # wall-clock period of the simulation step: 50 Hz
NS = 1_000_000_000
# Simulated time under --clock starts here (2023-11-14T22:13:20Z) rather than at 0: a stamp of 0
# means "no time" to many ROS tools, and a fixed epoch makes runs comparable.
CLOCK_EPOCH_NS = 1_700_000_000 * NS
TRUTH_PERIOD_NS = NS // 10
# A teleoperation stream that stops for this long (simulated s) stops the base, as a base
# controller's command timeout would.
CMD_VEL_TIMEOUT_NS = NS // 2

# The sensors' mounts on the base: x, y, z (m) and yaw (rad).
STATIC_MOUNTS = (("base_scan", (0.1, 0.0, 0.2, 0.0)), ("camera_link", (0.25, 0.0, 0.35, 0.0)))

ODOM_QOS = {
    # Best effort by default: robot drivers publish odometry so, and a subscriber asking for
    # reliable would not match, which is the mismatch this option lets a test reproduce.
    "best_effort": QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT),
    "reliable": QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE),
}
TF_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
# Latched: a subscriber arriving any time later gets the last message, as from tf2's static
# broadcaster and Nav2's map server.
LATCHED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
# Camera drivers publish frames best effort: a late frame is worth nothing.
CAMERA_QOS = QoSProfile(depth=2, reliability=ReliabilityPolicy.BEST_EFFORT)
# Best effort matches both reliable and best-effort command publishers (teleop tools differ).
CMD_VEL_SUBSCRIPTION_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)


@dataclass(frozen=True)
class SimOptions:
    """The simulator's settings, as ``dc sim``'s options give them."""

    rate: float = 1.0
    clock: bool = False
    duration: float | None = None
    loop: bool = False
    namespace: str = ""
    odom_qos: str = "best_effort"
    truth: Path | None = None
    wait_subscribers: float = 0.0
    camera_fps: float = 10.0
    camera_size: tuple[int, int] = (640, 480)


def _positive(text: str) -> float:
    value = float(text)
    if not value > 0.0 or math.isinf(value):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return value


def _non_negative(text: str) -> float:
    value = float(text)
    if not value >= 0.0 or math.isinf(value):
        raise argparse.ArgumentTypeError(f"must be a non-negative number, got {text}")
    return value


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="dc sim",
        description="A simulated robot in a warehouse: publishes odom, /tf, /tf_static, map, cmd_vel "
        "(and clock) while following a scripted route. ROS arguments go after --ros-args.",
    )
    parser.add_argument("--rate", type=_positive, default=1.0, help="simulated seconds per wall-clock second")
    parser.add_argument(
        "--clock", action="store_true", help="publish the simulated time on clock and stamp everything with it"
    )
    parser.add_argument("--duration", type=_positive, help="exit after this many simulated seconds")
    parser.add_argument("--loop", action="store_true", help="repeat the route instead of stopping at its end")
    parser.add_argument(
        "--namespace",
        default="",
        help="namespace of the node and its topics; /tf and /tf_static stay absolute unless remapped "
        "(--ros-args -r /tf:=tf -r /tf_static:=tf_static puts them in it)",
    )
    parser.add_argument("--odom-qos", choices=sorted(ODOM_QOS), default="best_effort", help="reliability of odom")
    parser.add_argument("--truth", type=Path, help="append the ground truth here, a JSON line per 0.1 s")
    parser.add_argument(
        "--wait-subscribers",
        type=_non_negative,
        default=0.0,
        metavar="S",
        help="wait up to S wall-clock seconds for a subscriber of odom before starting",
    )
    parser.add_argument(
        "--camera-fps",
        type=_non_negative,
        default=10.0,
        help="frames per wall-clock second on camera/image_raw (sensor_msgs/Image, bgr8); 0: no camera",
    )
    parser.add_argument("--camera-size", type=_size, default=(640, 480), metavar="WxH", help="frame size (640x480)")
    return parser


def _size(text: str) -> tuple[int, int]:
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT, got {text}") from None
    if width < 320 or height < 240:
        raise argparse.ArgumentTypeError(f"the shelf labels need at least 320x240, got {text}")
    return width, height


def parse_args(argv: Sequence[str]) -> SimOptions:
    """Options from ``dc sim``'s arguments (without any ``--ros-args`` part)."""
    args = build_parser().parse_args(list(argv))
    return SimOptions(
        rate=args.rate,
        clock=args.clock,
        duration=args.duration,
        loop=args.loop,
        namespace=args.namespace,
        odom_qos=args.odom_qos,
        truth=args.truth,
        wait_subscribers=args.wait_subscribers,
        camera_fps=args.camera_fps,
        camera_size=args.camera_size,
    )


def _codes_drawable(logger: Any) -> bool:
    """Whether zxing-cpp, which draws the shelves' codes, is installed: `make install` alone (the default job)
    leaves it out, and the robot without its camera still serves the demos that do not read codes."""
    try:
        import zxingcpp  # noqa: F401
    except ImportError:
        logger.warning(
            "no camera/image_raw: drawing the shelves' codes needs zxing-cpp "
            "(make install-demos, or pip install 'ros2-dc[camera]')"
        )
        return False
    return True


def _time_message(stamp_ns: int) -> Any:
    return Time(sec=stamp_ns // NS, nanosec=stamp_ns % NS)


def _set_yaw(orientation: Any, yaw: float) -> None:
    orientation.x, orientation.y = 0.0, 0.0
    orientation.z, orientation.w = math.sin(yaw / 2.0), math.cos(yaw / 2.0)


def _transform(stamp: Any, parent: str, child: str, x: float, y: float, z: float, yaw: float) -> Any:
    transform = TransformStamped()
    transform.header.stamp = stamp
    transform.header.frame_id = parent
    transform.child_frame_id = child
    transform.transform.translation.x, transform.transform.translation.y = x, y
    transform.transform.translation.z = z
    _set_yaw(transform.transform.rotation, yaw)
    return transform


def _pose_json(pose: Pose2D) -> dict[str, float]:
    return {"x": pose.x, "y": pose.y, "yaw": pose.yaw}


def occupancy_grid_message(grid: Grid, stamp: Any) -> Any:
    """``grid`` as a nav_msgs/OccupancyGrid in the map frame."""
    message = OccupancyGrid()
    message.header.stamp = stamp
    message.header.frame_id = "map"
    message.info.map_load_time = stamp
    message.info.resolution = grid.resolution
    message.info.width, message.info.height = grid.width, grid.height
    message.info.origin.position.x, message.info.origin.position.y = grid.origin.x, grid.origin.y
    _set_yaw(message.info.origin.orientation, grid.origin.yaw)
    message.data = grid.data
    return message


class SimRobot(Node):
    """The simulated robot; stepped by its own timer, so it only needs an executor to spin it."""

    def __init__(self, options: SimOptions, *, context: Context | None = None) -> None:
        super().__init__("dc_sim", namespace=options.namespace or None, context=context)
        self.options = options
        self.done = False
        self._step_ns = round(STEP_S * options.rate * NS)
        self._sim_ns = 0  # simulated time since the start
        self._next_truth_ns = 0
        self._map_to_odom = warehouse_start()
        self.base = DiffDrive()  # in the odom frame, which starts at the robot
        self.follower = RouteFollower(warehouse_route(), loop=options.loop)
        self.command = (0.0, 0.0)
        # Commands of another node on cmd_vel: set while that node publishes, with the simulated
        # time it arrived at (for the watchdog).
        self._teleop = False
        self._teleop_command: tuple[float, float, int] | None = None

        self._clock_publisher = self.create_publisher(ClockMessage, "clock", 10) if options.clock else None
        self._odom_publisher = self.create_publisher(Odometry, "odom", ODOM_QOS[options.odom_qos])
        self._tf_publisher = self.create_publisher(TFMessage, "/tf", TF_QOS)
        self._tf_static_publisher = self.create_publisher(TFMessage, "/tf_static", LATCHED_QOS)
        self._map_publisher = self.create_publisher(OccupancyGrid, "map", LATCHED_QOS)
        self._cmd_vel_publisher = self.create_publisher(Twist, "cmd_vel", 10)
        self._cmd_vel_subscription = self.create_subscription(
            Twist, "cmd_vel", self._on_cmd_vel, CMD_VEL_SUBSCRIPTION_QOS
        )
        self._truth: IO[str] | None = options.truth.open("a", encoding="utf-8") if options.truth else None
        self._camera: CameraView | None = None
        self._camera_timer: Any = None
        if options.camera_fps > 0 and _codes_drawable(self.get_logger()):
            self._camera = CameraView(self.follower.waypoints, *options.camera_size)
            self._image_publisher = self.create_publisher(Image, "camera/image_raw", CAMERA_QOS)
            self._camera_timer = self.create_timer(
                1.0 / options.camera_fps, self._publish_frame, clock=Clock(clock_type=ClockType.STEADY_TIME)
            )

        start = _time_message(self._stamp_ns())
        self._tf_static_publisher.publish(
            TFMessage(transforms=[_transform(start, "base_link", child, *mount) for child, mount in STATIC_MOUNTS])
        )
        self._map_publisher.publish(occupancy_grid_message(warehouse_grid(), start))

        self._waiting_until = time.monotonic() + options.wait_subscribers if options.wait_subscribers > 0 else None
        # Steady time: the step must keep its wall-clock pace whatever the node's clock follows
        # (a use_sim_time parameter would otherwise make the simulator wait for its own clock).
        self._timer = self.create_timer(STEP_S, self._step, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.get_logger().info(
            f"sim: route of {len(self.follower.waypoints)} waypoints{' (looping)' if options.loop else ''}, "
            f"{options.rate:g}x real time, /clock {'on' if options.clock else 'off'}, "
            f"odom {options.odom_qos}"
            + (f", stopping after {options.duration:g} s" if options.duration else "")
            + (f", truth to {options.truth}" if options.truth else "")
        )
        if self._waiting_until is not None:
            self.get_logger().info(f"sim: waiting up to {options.wait_subscribers:g} s for a subscriber of odom")

    def destroy_node(self) -> None:
        if self._truth is not None:
            self._truth.close()
            self._truth = None
        super().destroy_node()

    @property
    def sim_time(self) -> float:
        """Simulated seconds since the start."""
        return self._sim_ns / NS

    @property
    def map_pose(self) -> Pose2D:
        """The pose of base_link in the map: map -> odom composed with the odometry."""
        return self._map_to_odom.compose(self.base.pose)

    def _stamp_ns(self) -> int:
        if self.options.clock:
            return CLOCK_EPOCH_NS + self._sim_ns
        return int(self.get_clock().now().nanoseconds)

    def _on_cmd_vel(self, message: Any) -> None:
        # While the route drives, what arrives here is the simulator's own publication: ignored.
        if self._teleop:
            self._teleop_command = (float(message.linear.x), float(message.angular.z), self._sim_ns)

    def _waiting(self) -> bool:
        if self._waiting_until is None:
            return False
        if self.count_subscribers("odom") > 0 or time.monotonic() >= self._waiting_until:
            self._waiting_until = None
            self.get_logger().info(f"sim: {self.count_subscribers('odom')} subscriber(s) of odom, starting")
            return False
        return True

    def _next_command(self, dt: float) -> tuple[float, float]:
        # The simulator's own publisher is one; any other means someone else drives.
        teleop = self.count_publishers("cmd_vel") > 1
        if teleop != self._teleop:
            self._teleop = teleop
            self._teleop_command = None
            self.get_logger().info("sim: cmd_vel from another node, route paused" if teleop else "sim: route resumed")
        if self._teleop:
            if self._teleop_command is None:
                return 0.0, 0.0
            v, w, received_ns = self._teleop_command
            return (v, w) if self._sim_ns - received_ns <= CMD_VEL_TIMEOUT_NS else (0.0, 0.0)
        stopped_before = self.follower.stopped_at
        command = self.follower.command(self.map_pose, dt)
        if self.follower.stopped_at is not None and stopped_before is None:
            self.get_logger().info(f"sim: at waypoint {self.follower.stopped_at}")
        twist = Twist()
        twist.linear.x, twist.angular.z = command
        self._cmd_vel_publisher.publish(twist)
        return command

    def _step(self) -> None:
        if self.done:
            return
        if self._waiting():
            if self._clock_publisher is not None:
                # Time stands still until the start, but sim-time subscribers need a valid clock.
                self._clock_publisher.publish(ClockMessage(clock=_time_message(self._stamp_ns())))
            return

        dt = self._step_ns / NS
        self.command = self._next_command(dt)
        self.base.step(*self.command, dt)
        self._sim_ns += self._step_ns

        stamp_ns = self._stamp_ns()
        stamp = _time_message(stamp_ns)
        if self._clock_publisher is not None:
            # Before anything stamped with it, so sim-time subscribers never see a stamp from their future.
            self._clock_publisher.publish(ClockMessage(clock=stamp))
        self._publish_odometry(stamp)
        if self._truth is not None and self._sim_ns >= self._next_truth_ns:
            self._write_truth(stamp_ns)
            while self._next_truth_ns <= self._sim_ns:
                self._next_truth_ns += TRUTH_PERIOD_NS

        if self.options.duration is not None and self._sim_ns >= round(self.options.duration * NS):
            self.done = True
            self.get_logger().info(f"sim: {self.sim_time:g} s simulated, {self.base.distance:.2f} m driven, done")

    def _publish_odometry(self, stamp: Any) -> None:
        pose = self.base.pose
        v, w = self.command
        odometry = Odometry()
        odometry.header.stamp = stamp
        odometry.header.frame_id = "odom"
        odometry.child_frame_id = "base_link"
        odometry.pose.pose.position.x, odometry.pose.pose.position.y = pose.x, pose.y
        _set_yaw(odometry.pose.pose.orientation, pose.yaw)
        odometry.twist.twist.linear.x, odometry.twist.twist.angular.z = v, w
        self._odom_publisher.publish(odometry)
        offset = self._map_to_odom
        self._tf_publisher.publish(
            TFMessage(
                transforms=[
                    _transform(stamp, "odom", "base_link", pose.x, pose.y, 0.0, pose.yaw),
                    _transform(stamp, "map", "odom", offset.x, offset.y, 0.0, offset.yaw),
                ]
            )
        )

    def _publish_frame(self) -> None:
        assert self._camera is not None
        if self.done or self._waiting_until is not None:
            return
        frame = self._camera.frame(self._camera.label_in_view(self.map_pose))
        image = Image()
        image.header.stamp = _time_message(self._stamp_ns())
        image.header.frame_id = "camera_link"
        image.height, image.width = frame.shape[:2]
        image.encoding = "bgr8"
        image.step = frame.shape[1] * 3
        image.data = frame.tobytes()
        self._image_publisher.publish(image)

    def _write_truth(self, stamp_ns: int) -> None:
        assert self._truth is not None
        v, w = self.command
        line = {
            "t": stamp_ns / NS,
            "odom": _pose_json(self.base.pose),
            "map": _pose_json(self.map_pose),
            "distance": self.base.distance,
            "v": v,
            "w": w,
            "stopped_at": self.follower.stopped_at,
            "label_in_view": self._camera.label_in_view(self.map_pose) if self._camera is not None else None,
        }
        self._truth.write(json.dumps(line) + "\n")
        self._truth.flush()  # a reader (a test, a script) may follow the file while the sim runs


def main(argv: Sequence[str] | None = None) -> int:
    """``dc sim``: run the simulated robot until ``--duration`` or SIGINT/SIGTERM; returns 0 then."""
    arguments = list(sys.argv[1:] if argv is None else argv)
    ros_arguments: list[str] = []
    if "--ros-args" in arguments:
        split = arguments.index("--ros-args")
        arguments, ros_arguments = arguments[:split], arguments[split:]
    options = parse_args(arguments)

    stop = StopRequest()

    def request_stop(signum: int, frame: FrameType | None) -> None:
        stop.on_signal(signum, frame)  # a flag, no lock: safe under a burst of signals (dc_core.signals)

    # Our own handlers rather than rclpy's: they only ask the loop to end, which then tears down
    # in order (truth file closed, node destroyed, context shut down) and exits 0.
    handled = (signal.SIGINT, signal.SIGTERM)
    previous = (
        {signum: signal.signal(signum, request_stop) for signum in handled}
        if threading.current_thread() is threading.main_thread()
        else {}
    )
    context = Context()
    rclpy.init(args=["dc sim", *ros_arguments], context=context, signal_handler_options=SignalHandlerOptions.NO)
    try:
        try:
            node = SimRobot(options, context=context)
        except OSError as exc:
            print(f"dc sim: {exc}", file=sys.stderr)
            return 2
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        try:
            while not stop.is_set() and not node.done and context.ok():
                executor.spin_once(timeout_sec=0.1)
        finally:
            executor.shutdown()
            node.destroy_node()
    finally:
        context.try_shutdown()
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    return 0
