"""Moving: whether the robot moves, from odometry speed with a hysteresis counter.

The decision lives in :class:`MovingHysteresis`, a pure state machine fed with speeds; the
plugin only subscribes to ``nav_msgs/msg/Odometry`` and feeds it.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from nav_msgs.msg import Odometry

from dc_core.condition import Condition, ConditionContext
from dc_core.errors import PluginError
from dc_core.params import param
from dc_core.qos import SENSOR_QOS
from dc_core.topics import topic_param


@dataclass(frozen=True, kw_only=True)
class MovingParams:
    odom_topic: str = topic_param("/odom", doc="nav_msgs/msg/Odometry topic whose twist gives the speed")
    speed_threshold: float = param(0.2, minimum=0.0, doc="Speed (m/s) above which a message counts as moving")
    count_limit: int = param(8, minimum=1, doc="Bound of the counter (messages), in both directions")
    count_hysteresis: int = param(
        5, minimum=1, doc="Counter value (messages) at which the state switches; at most count_limit"
    )


class MovingHysteresis:
    """Counter over successive speeds: +1 above the threshold, -1 otherwise, clamped to the limit.

    Active once the counter reaches ``+hysteresis``, inactive once it reaches ``-hysteresis``;
    in between the previous state holds. It starts inactive with the counter at 0.
    """

    def __init__(self, speed_threshold: float, count_limit: int, count_hysteresis: int) -> None:
        if not 1 <= count_hysteresis <= count_limit:
            raise ValueError(
                f"count_hysteresis must be between 1 and count_limit ({count_limit}), got {count_hysteresis}"
            )
        self.speed_threshold = speed_threshold
        self.count_limit = count_limit
        self.count_hysteresis = count_hysteresis
        self.counter = 0
        self.active = False

    def update(self, speed: float) -> bool:
        """Account for one speed measurement; returns the state after it."""
        step = 1 if speed > self.speed_threshold else -1
        self.counter = max(-self.count_limit, min(self.count_limit, self.counter + step))
        if self.counter >= self.count_hysteresis:
            self.active = True
        elif self.counter <= -self.count_hysteresis:
            self.active = False
        return self.active


def linear_speed(odometry: Any) -> float:
    """Norm of the linear velocity of a nav_msgs/msg/Odometry message."""
    linear = odometry.twist.twist.linear
    return math.sqrt(linear.x * linear.x + linear.y * linear.y + linear.z * linear.z)


class Moving(Condition[MovingParams]):
    """Robot is moving: odometry speed above a threshold, with hysteresis."""

    needs_sample = False

    def __init__(self, context: ConditionContext, params: MovingParams) -> None:
        super().__init__(context, params)
        self._lock = threading.Lock()
        self._hysteresis: MovingHysteresis | None = None
        self._subscription: Any = None

    def _new_hysteresis(self) -> MovingHysteresis:
        p: MovingParams = self.params
        try:
            return MovingHysteresis(p.speed_threshold, p.count_limit, p.count_hysteresis)
        except ValueError as exc:
            raise PluginError(f"{self.context.name}.count_hysteresis: {exc}") from None

    def on_configure(self) -> None:
        if self.context.node is None:
            raise PluginError(f"{self.context.name}: Moving needs a ROS node to subscribe to odometry")
        self.on_cleanup()  # a second configure replaces the subscription rather than adding one
        with self._lock:
            self._hysteresis = self._new_hysteresis()
        topic = self.params.odom_topic
        # (A lost message only delays the decision by one count.)
        self._subscription = self.context.subscribe(Odometry, topic, self._on_odometry, SENSOR_QOS)

    def on_cleanup(self) -> None:
        if self._subscription is not None:
            self.context.unsubscribe(self._subscription)
            self._subscription = None
        with self._lock:
            self._hysteresis = None

    def _on_odometry(self, message: Any, info: Any = None) -> None:
        speed = linear_speed(message)
        with self._lock:
            if self._hysteresis is not None:
                self._hysteresis.update(speed)

    def evaluate(self, sample: Mapping[str, Any] | None) -> bool:
        with self._lock:
            return self._hysteresis is not None and self._hysteresis.active
