"""CmdVel measurement: the velocity commanded to the robot (geometry_msgs/Twist or TwistStamped on /cmd_vel).

Jazzy's diff_drive_controller reads TwistStamped, so what drives it (Nav2 with
``enable_stamped_cmd_vel``, a stamped teleop) publishes that; older stacks publish Twist. A
subscription of the other type matches nothing. With ``message_type:
auto`` the type is read from the graph: at configure, and again at each poll that found no new
message (a subscription that receives has the right type, and a poll is a cheap moment to look).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from geometry_msgs.msg import Twist, TwistStamped

from dc_core.params import param
from dc_core.rostime import stamp_ns
from dc_core.topics import topic_param
from dc_measurements.velocity import LatestTwistMeasurement, repeat_last_param

AUTO = "auto"
TWIST = "geometry_msgs/msg/Twist"
TWIST_STAMPED = "geometry_msgs/msg/TwistStamped"
_MESSAGE_TYPES = {TWIST: Twist, TWIST_STAMPED: TwistStamped}


@dataclass(frozen=True, kw_only=True)
class CmdVelParams:
    topic: str = topic_param("/cmd_vel", doc="geometry_msgs/msg/Twist or TwistStamped topic of the commands")
    message_type: str = param(
        AUTO,
        choices=(AUTO, TWIST, TWIST_STAMPED),
        doc="Type of the commands; auto: the type the topic's publishers use (Twist while there is none)",
    )
    repeat_last: bool = repeat_last_param()


class CmdVel(LatestTwistMeasurement[CmdVelParams]):
    """Velocity commanded to the robot: linear and angular vectors and the planar speed, from /cmd_vel."""

    message_type = Twist

    def __init__(self, context: Any, params: CmdVelParams) -> None:
        super().__init__(context, params)
        self.subscribed_type = ""
        self._received_at_last_look = 0
        self._mixed_warned = False

    @property
    def topic(self) -> str:
        return self.params.topic

    @staticmethod
    def twist_of(message: Any) -> Any:
        return message.twist if isinstance(message, TwistStamped) else message

    @staticmethod
    def stamp_of(message: Any) -> int | None:
        return (stamp_ns(message.header.stamp) or None) if isinstance(message, TwistStamped) else None

    def on_configure(self) -> None:
        self.on_cleanup()
        wanted = self.params.message_type
        self._follow(self._published_type() or TWIST if wanted == AUTO else wanted)

    def on_cleanup(self) -> None:
        super().on_cleanup()
        self.subscribed_type = ""
        self._received_at_last_look = 0

    def _follow(self, type_name: str) -> None:
        if type_name == self.subscribed_type:
            return
        if self.subscribed_type:
            self.context.logger.info(
                f"measurement {self.context.name}: {self.topic} is published as {type_name}: subscribed to it "
                f"instead of {self.subscribed_type}"
            )
        self.subscribe(_MESSAGE_TYPES[type_name])
        self.subscribed_type = type_name

    def _published_type(self) -> str | None:
        """The one command type the topic's publishers use now; None with no publisher, or with both types."""
        node = self.context.node
        if node is None:
            return None
        name = node.resolve_topic_name(self.topic)
        types: set[str] = {str(info.topic_type) for info in node.get_publishers_info_by_topic(name)}
        types &= set(_MESSAGE_TYPES)
        if len(types) == 1:
            return types.pop()
        if types and not self._mixed_warned:
            self._mixed_warned = True
            self.context.logger.warning(
                f"measurement {self.context.name}: {self.topic} has Twist and TwistStamped publishers; "
                f"reading {self.subscribed_type or TWIST} only"
            )
        return None

    def collect_stamped(self) -> tuple[dict[str, Any] | None, int | None, str | None]:
        if self.params.message_type == AUTO:
            received = self.counters()["received"]
            if received == self._received_at_last_look:
                published = self._published_type()
                if published is not None:
                    self._follow(published)
            self._received_at_last_look = received
        return super().collect_stamped()
