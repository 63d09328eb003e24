"""Speed measurement: the robot's velocity as its odometry reports it (nav_msgs/Odometry twist)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from nav_msgs.msg import Odometry

from dc_core.rostime import stamp_ns
from dc_core.topics import topic_param
from dc_measurements.velocity import LatestTwistMeasurement, repeat_last_param


@dataclass(frozen=True, kw_only=True)
class SpeedParams:
    odom_topic: str = topic_param("/odom", doc="nav_msgs/msg/Odometry topic whose twist is the robot's velocity")
    repeat_last: bool = repeat_last_param()


class Speed(LatestTwistMeasurement[SpeedParams]):
    """Robot velocity from odometry: linear and angular vectors (in the odometry's child frame) and planar speed."""

    message_type = Odometry

    @property
    def topic(self) -> str:
        return self.params.odom_topic

    @staticmethod
    def twist_of(message: Any) -> Any:
        return message.twist.twist

    @staticmethod
    def stamp_of(message: Any) -> int | None:
        return stamp_ns(message.header.stamp) or None
