"""Kinematics of the simulated robot: a differential-drive base and a waypoint follower.

Pure Python, without ROS, so that the motion the simulator publishes can be predicted exactly by
tests: :class:`DiffDrive` integrates a unicycle in closed form (an arc per step, not an Euler
approximation), so a full circle closes up to rounding and the path length is known in advance;
:class:`RouteFollower` produces the commands a simple navigation stack would (turn in place, drive,
stop at a waypoint for a while) so that DC's measurements see realistic phases of motion.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

# Below this angular speed (rad/s) an arc of a step is indistinguishable from a straight line, and
# the closed-form arc would divide by almost zero.
STRAIGHT_W = 1e-9


def wrap_angle(angle: float) -> float:
    """``angle`` brought into (-pi, pi]."""
    wrapped = math.remainder(angle, math.tau)
    # remainder() gives [-pi, pi]: the half-open interval keeps one representation of the turn.
    return math.pi if wrapped <= -math.pi else wrapped


@dataclass(frozen=True)
class Pose2D:
    """A pose in the plane: position (m) and heading (rad, counter-clockwise from +x)."""

    x: float = 0.0
    y: float = 0.0
    yaw: float = 0.0

    def compose(self, other: Pose2D) -> Pose2D:
        """``self ∘ other``: ``other`` (expressed in this pose's frame) in this pose's parent frame."""
        cos_yaw, sin_yaw = math.cos(self.yaw), math.sin(self.yaw)
        return Pose2D(
            self.x + cos_yaw * other.x - sin_yaw * other.y,
            self.y + sin_yaw * other.x + cos_yaw * other.y,
            wrap_angle(self.yaw + other.yaw),
        )


class DiffDrive:
    """A differential-drive base: its pose and the length of the path it has driven."""

    def __init__(self, pose: Pose2D | None = None) -> None:
        self.pose = pose if pose is not None else Pose2D()
        self.distance = 0.0

    def step(self, v: float, w: float, dt: float) -> Pose2D:
        """Drive at linear speed ``v`` (m/s) and angular speed ``w`` (rad/s) for ``dt`` seconds.

        Constant speeds over a step trace an arc (or a segment), integrated exactly; returns the new pose.
        """
        x, y, yaw = self.pose.x, self.pose.y, self.pose.yaw
        if abs(w) < STRAIGHT_W:
            x += v * dt * math.cos(yaw)
            y += v * dt * math.sin(yaw)
        else:
            radius = v / w
            end_yaw = yaw + w * dt
            x += radius * (math.sin(end_yaw) - math.sin(yaw))
            y -= radius * (math.cos(end_yaw) - math.cos(yaw))
            yaw = end_yaw
        self.pose = Pose2D(x, y, wrap_angle(yaw))
        self.distance += abs(v) * dt
        return self.pose


@dataclass(frozen=True)
class Waypoint:
    """A place on the route (m, in the follower's frame) and how long to stop there (s)."""

    x: float
    y: float
    stop_s: float = 0.0


class RouteFollower:
    """Commands (v, w) that take a base through waypoints in order, stopping at each one.

    Towards each waypoint it first turns in place until it faces it, then drives with a speed
    proportional to the remaining distance (capped at ``v_max``) and a proportional heading
    correction. Within ``position_tolerance`` it stops and dwells for the waypoint's ``stop_s``
    (counted with the ``dt`` of the calls, so simulated time, not wall time), then heads for the next.
    """

    # Gains (1/s) of the proportional laws; k_w > k_v so that the heading converges before the
    # distance does and the base does not orbit the waypoint.
    K_V = 1.0
    K_W = 2.0
    # Facing the waypoint within this (rad) ends the turn in place.
    HEADING_TOLERANCE = 0.05
    # Pushed off course by more than this (rad) while driving, the base turns in place again
    # rather than drive a wide arc.
    REALIGN = math.pi / 4
    # Dwell left below this (s) counts as done: accumulated float steps never hit 0 exactly.
    DWELL_EPSILON = 1e-9

    def __init__(
        self,
        waypoints: Sequence[Waypoint],
        v_max: float = 0.5,
        w_max: float = 1.0,
        position_tolerance: float = 0.05,
        loop: bool = False,
    ) -> None:
        if not waypoints:
            raise ValueError("a route needs at least one waypoint")
        self.waypoints = list(waypoints)
        self.v_max = v_max
        self.w_max = w_max
        self.position_tolerance = position_tolerance
        self.loop = loop
        self.target = 0
        self.stopped_at: int | None = None
        self.finished = False
        self._turning = True
        self._dwell_left = 0.0

    def _clamp_w(self, w: float) -> float:
        return max(-self.w_max, min(self.w_max, w))

    def _release(self) -> None:
        """Leave the waypoint dwelt at for the next one (or finish the route)."""
        self.stopped_at = None
        self._turning = True
        self.target += 1
        if self.target == len(self.waypoints):
            if self.loop:
                self.target = 0
            else:
                self.finished = True

    def command(self, pose: Pose2D, dt: float) -> tuple[float, float]:
        """The (v, w) to apply for the next ``dt`` seconds from ``pose``."""
        if self.stopped_at is not None:
            if self._dwell_left > self.DWELL_EPSILON:
                self._dwell_left -= dt
                return 0.0, 0.0
            self._release()
        if self.finished:
            return 0.0, 0.0

        waypoint = self.waypoints[self.target]
        dx, dy = waypoint.x - pose.x, waypoint.y - pose.y
        distance = math.hypot(dx, dy)
        if distance < self.position_tolerance:
            self.stopped_at = self.target
            # This call's (0, 0) already holds the base still for dt (so a waypoint without a stop
            # still costs one step: the stop is visible in stopped_at).
            self._dwell_left = waypoint.stop_s - dt
            return 0.0, 0.0

        error = wrap_angle(math.atan2(dy, dx) - pose.yaw)
        if not self._turning and abs(error) > self.REALIGN:
            self._turning = True
        if self._turning:
            if abs(error) >= self.HEADING_TOLERANCE:
                return 0.0, self._clamp_w(self.K_W * error)
            self._turning = False
        return min(self.v_max, self.K_V * distance), self._clamp_w(self.K_W * error)
