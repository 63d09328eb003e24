"""CmdVel measurement: the velocity commanded to the robot (geometry_msgs/Twist on /cmd_vel)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from geometry_msgs.msg import Twist

from dc_core.measurement import Measurement, MeasurementContext
from dc_core.rostime import now_ns
from dc_measurements.velocity import SENSOR_QOS, LatestTwist, repeat_last_param, topic_param


@dataclass(frozen=True, kw_only=True)
class CmdVelParams:
    topic: str = topic_param("/cmd_vel", "geometry_msgs/msg/Twist topic of the commands")
    repeat_last: bool = repeat_last_param()


class CmdVel(Measurement[CmdVelParams]):
    """Velocity commanded to the robot: linear and angular vectors and the planar speed, from /cmd_vel."""

    def __init__(self, context: MeasurementContext, params: CmdVelParams) -> None:
        super().__init__(context, params)
        self._latest = LatestTwist()
        self._subscription: Any = None

    def on_configure(self) -> None:
        self.on_cleanup()
        self._subscription = self.context.subscribe(Twist, self.params.topic, self._on_twist, SENSOR_QOS)

    def on_cleanup(self) -> None:
        if self._subscription is not None:
            self.context.unsubscribe(self._subscription)
            self._subscription = None
        self._latest.reset()

    def _on_twist(self, message: Any, info: Any = None) -> None:
        self._latest.update(message, now_ns(self.context.node))

    def collect(self) -> dict[str, Any] | None:
        return self._latest.take(now_ns(self.context.node), self.params.repeat_last)

    def counters(self) -> dict[str, int]:
        return {"received": self._latest.received}
