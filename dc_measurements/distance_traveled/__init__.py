"""DistanceTraveled measurement: the distance the robot has traveled since DC started, cumulative.

The original reported the distance since the previous sample under a schema that says "total",
and read an uninitialised timeout. Here every pose the robot reports — each /tf update of the chain
``global_frame`` → ``robot_base_frame``, or each odometry message — feeds an :class:`Odometer`, and a
poll reports its total. Poses are not taken at poll times, so corners between two polls count.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from nav_msgs.msg import Odometry

from dc_core.errors import PluginError
from dc_core.measurement import Measurement, MeasurementContext
from dc_core.params import compat_param, param
from dc_core.qos import SENSOR_QOS
from dc_core.rostime import stamp_ns
from dc_core.tf import TransformBuffer, TransformError
from dc_core.tf_listener import TfListener
from dc_core.topics import topic_param

# Odometry stamped this far behind the previous message means its time restarted (a bag replayed
# without use_sim_time), not a late message: one topic from one publisher, so stamps are monotonic.
ODOM_TIME_JUMP_BACK_NS = 1_000_000_000


@dataclass(frozen=True, kw_only=True)
class DistanceTraveledParams:
    source: str = param("tf", choices=("tf", "odom"), doc="Where poses come from: TF (the frames below) or odometry")
    global_frame: str = param("map", doc="Frame the robot's path is measured in (source tf)")
    robot_base_frame: str = param("base_link", doc="The robot's frame (source tf)")
    odom_topic: str = topic_param("/odom", doc="nav_msgs/msg/Odometry topic (source odom)")
    transform_timeout: float = compat_param(0.1, "poses are taken as TF updates arrive", minimum=0.0)
    min_step: float = param(
        0.01,
        minimum=0.0,
        doc="Metres the robot must move from the last counted pose before a move counts (jitter of a standing "
        "robot adds nothing; slow motion is counted once it adds up)",
    )
    max_step: float = param(
        0.0,
        minimum=0.0,
        doc="A jump longer than this (m) between two poses is a relocalisation, not travel, and is not counted "
        "(0: no limit)",
    )


class Odometer:
    """Path length of a sequence of planar positions, with a minimum step against jitter.

    A move counts once the robot is ``min_step`` away from the last counted position, and then counts
    in full: nothing is lost, only deferred. A move longer than ``max_step`` (when set) is a jump of the
    estimate (a localiser correcting itself): the position is taken as the new start, not counted.
    """

    def __init__(self, min_step: float, max_step: float = 0.0) -> None:
        self.min_step = min_step
        self.max_step = max_step
        self.total = 0.0
        self.jumps = 0
        self._anchor: tuple[float, float] | None = None

    def add(self, x: float, y: float) -> None:
        if self._anchor is None:
            self._anchor = (x, y)
            return
        step = math.hypot(x - self._anchor[0], y - self._anchor[1])
        if step < self.min_step:
            return
        if self.max_step and step > self.max_step:
            self.jumps += 1
        else:
            self.total += step
        self._anchor = (x, y)

    def restart_path(self) -> None:
        """The next position starts a new path (time restarted): the total stays."""
        self._anchor = None


class DistanceTraveled(Measurement[DistanceTraveledParams]):
    """Total distance traveled by the robot since DC started (m), from TF or odometry."""

    def __init__(self, context: MeasurementContext, params: DistanceTraveledParams) -> None:
        super().__init__(context, params)
        self.odometer = Odometer(params.min_step, params.max_step)
        self.buffer = TransformBuffer()
        self._listener = TfListener(context, self.buffer, self._on_tf_update)
        self._subscription: Any = None
        self._last_pose_ns = 0
        self._time_jumps_seen = 0
        self.no_transform = 0

    def on_configure(self) -> None:
        p = self.params
        if p.source == "tf" and p.global_frame.strip("/") == p.robot_base_frame.strip("/"):
            raise PluginError(f"{self.context.name}: global_frame and robot_base_frame are both {p.global_frame!r}")
        self.on_cleanup()
        self.odometer = Odometer(p.min_step, p.max_step)
        if p.source == "tf":
            self._listener.start()
        else:
            self._subscription = self.context.subscribe(Odometry, p.odom_topic, self._on_odometry, SENSOR_QOS)

    def on_cleanup(self) -> None:
        self._listener.stop()
        if self._subscription is not None:
            self.context.unsubscribe(self._subscription)
            self._subscription = None
        self.buffer.clear()
        self._last_pose_ns = 0

    def _on_tf_update(self) -> None:
        if self._listener.time_jumps != self._time_jumps_seen:
            self._time_jumps_seen = self._listener.time_jumps
            self._last_pose_ns = 0
            self.odometer.restart_path()
        p = self.params
        try:
            at = self.buffer.latest_time(p.global_frame, p.robot_base_frame)
            if at <= self._last_pose_ns:
                return  # this update was of other frames
            pose = self.buffer.lookup(p.global_frame, p.robot_base_frame, at)
        except TransformError:
            self.no_transform += 1
            return
        self._last_pose_ns = at
        self.odometer.add(pose.translation[0], pose.translation[1])

    def _on_odometry(self, message: Any, info: Any = None) -> None:
        at = stamp_ns(message.header.stamp)
        if at < self._last_pose_ns - ODOM_TIME_JUMP_BACK_NS:
            self.odometer.restart_path()
        self._last_pose_ns = at
        position = message.pose.pose.position
        self.odometer.add(float(position.x), float(position.y))

    def collect(self) -> dict[str, Any] | None:
        return {"distance_traveled": self.odometer.total}

    def counters(self) -> dict[str, int]:
        return {
            "jumps": self.odometer.jumps,
            "no_transform": self.no_transform,
            "tf_time_jumps": self._listener.time_jumps,
            "tf_old_data": self._listener.old_data,
        }
