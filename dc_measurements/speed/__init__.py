"""Speed measurement: the robot's velocity as its odometry reports it (nav_msgs/Odometry twist)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from nav_msgs.msg import Odometry

from dc_core.measurement import Measurement, MeasurementContext
from dc_core.rostime import now_ns
from dc_measurements.velocity import SENSOR_QOS, LatestTwist, repeat_last_param, topic_param


@dataclass(frozen=True, kw_only=True)
class SpeedParams:
    odom_topic: str = topic_param("/odom", "nav_msgs/msg/Odometry topic whose twist is the robot's velocity")
    repeat_last: bool = repeat_last_param()


class Speed(Measurement[SpeedParams]):
    """Robot velocity from odometry: linear and angular vectors (in the odometry's child frame) and planar speed."""

    def __init__(self, context: MeasurementContext, params: SpeedParams) -> None:
        super().__init__(context, params)
        self._latest = LatestTwist()
        self._subscription: Any = None

    def on_configure(self) -> None:
        self.on_cleanup()
        self._subscription = self.context.subscribe(Odometry, self.params.odom_topic, self._on_odometry, SENSOR_QOS)

    def on_cleanup(self) -> None:
        if self._subscription is not None:
            self.context.unsubscribe(self._subscription)
            self._subscription = None
        self._latest.reset()

    def _on_odometry(self, message: Any, info: Any = None) -> None:
        self._latest.update(message.twist.twist, now_ns(self.context.node))

    def collect(self) -> dict[str, Any] | None:
        return self._latest.take(now_ns(self.context.node), self.params.repeat_last)

    def counters(self) -> dict[str, int]:
        return {"received": self._latest.received}
