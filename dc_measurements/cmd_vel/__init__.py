"""CmdVel measurement: the velocity commanded to the robot (geometry_msgs/Twist on /cmd_vel)."""

from __future__ import annotations

from dataclasses import dataclass

from geometry_msgs.msg import Twist

from dc_measurements.velocity import LatestTwistMeasurement, repeat_last_param, topic_param


@dataclass(frozen=True, kw_only=True)
class CmdVelParams:
    topic: str = topic_param("/cmd_vel", "geometry_msgs/msg/Twist topic of the commands")
    repeat_last: bool = repeat_last_param()


class CmdVel(LatestTwistMeasurement[CmdVelParams]):
    """Velocity commanded to the robot: linear and angular vectors and the planar speed, from /cmd_vel."""

    message_type = Twist

    @property
    def topic(self) -> str:
        return self.params.topic
