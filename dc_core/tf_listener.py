"""Fill a :class:`dc_core.tf.TransformBuffer` from ``/tf`` and ``/tf_static``, as tf2_ros' listener does.

``/tf_static`` is read with TRANSIENT_LOCAL durability, so the statics a robot published before DC
started still arrive. ``/tf`` is read best effort, which matches reliable and best-effort
publishers alike.

The moving links' history is cleared only when the node's clock jumps back (``/clock`` going back
under ``use_sim_time``: a bag restarted with ``--loop``, a simulator reset) or changes source, as
tf2_ros' buffer does: interpolating between two runs would invent a path. Stamps alone say nothing
about time going back: each link has its own history, and a localiser such as AMCL post-dates
``map`` → ``odom`` by its ``transform_tolerance`` while odometry arrives late, so a message older
than another link's newest is normal. A sample older than its own link's history (``cache_s``) is
ignored, counted and logged, as tf2's ``TF_OLD_DATA``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from rclpy.clock import ClockChange, JumpHandle, JumpThreshold, TimeJump
from rclpy.duration import Duration
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from dc_core.logs import BurstLog
from dc_core.plugin import PluginContext
from dc_core.rostime import stamp_ns
from dc_core.tf import Transform, TransformBuffer

TF_TOPIC = "/tf"
TF_STATIC_TOPIC = "/tf_static"
TF_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)
TF_STATIC_QOS = QoSProfile(
    depth=100, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL
)
# Any step back of the clock clears, as tf2_ros: a bag restarting is never a matter of degree.
_CLOCK_JUMP = JumpThreshold(min_forward=None, min_backward=Duration(nanoseconds=-1), on_clock_change=True)


def transform_from_msg(msg: Any) -> Transform:
    """A geometry_msgs/Transform as a :class:`Transform`."""
    t, r = msg.translation, msg.rotation
    return Transform((t.x, t.y, t.z), (r.x, r.y, r.z, r.w))


class TfListener:
    """Subscriptions of one plugin to /tf and /tf_static, feeding ``buffer``, and a jump callback
    on the node's clock that clears it."""

    def __init__(
        self, context: PluginContext, buffer: TransformBuffer, on_update: Callable[[], None] | None = None
    ) -> None:
        self.context = context
        self.buffer = buffer
        # Called after each /tf message was added (on the thread that takes messages).
        self.on_update = on_update
        # Times the history was cleared because the clock jumped back or changed source.
        self.time_jumps = 0
        # Samples ignored because they were older than their link's history.
        self.old_data = 0
        self._old_data_log = BurstLog(context.logger.warning, "/tf samples older than their link's history ignored")
        self._subscriptions: list[Any] = []
        self._jump_handle: JumpHandle | None = None

    def start(self) -> None:
        from tf2_msgs.msg import TFMessage

        self.stop()
        self._subscriptions = [
            self.context.subscribe(TFMessage, TF_TOPIC, self._on_tf, TF_QOS),
            self.context.subscribe(TFMessage, TF_STATIC_TOPIC, self._on_tf_static, TF_STATIC_QOS),
        ]
        node = self.context.node
        if node is not None:
            self._jump_handle = node.get_clock().create_jump_callback(_CLOCK_JUMP, post_callback=self._on_time_jump)

    def stop(self) -> None:
        for subscription in self._subscriptions:
            self.context.unsubscribe(subscription)
        self._subscriptions = []
        if self._jump_handle is not None:
            self._jump_handle.unregister()
            self._jump_handle = None

    def _on_time_jump(self, jump: TimeJump) -> None:
        # rclpy calls this from inside the clock's update; it must not raise (later callbacks would be skipped).
        try:
            if jump.clock_change in (ClockChange.ROS_TIME_ACTIVATED, ClockChange.ROS_TIME_DEACTIVATED):
                reason = "the clock changed source (use_sim_time switched)"
            elif jump.delta.nanoseconds < 0:
                reason = f"the clock jumped back {-jump.delta.nanoseconds / 1e9:.1f} s"
            else:
                return
            self.buffer.clear()
            self.time_jumps += 1
            self.context.logger.warning(f"{reason}: transform history cleared")
        except Exception as exc:  # a failure here would silence the clock's other callbacks
            self.context.logger.error(f"clearing the transform history failed: {exc!r}")

    def _on_tf(self, message: Any, info: Any = None) -> None:
        self._add(message, static=False)
        if self.on_update is not None:
            self.on_update()

    def _on_tf_static(self, message: Any, info: Any = None) -> None:
        self._add(message, static=True)

    def _add(self, message: Any, *, static: bool) -> None:
        self._old_data_log.tick()
        for transform in message.transforms:
            parent, child = transform.header.frame_id, transform.child_frame_id
            stamp = stamp_ns(transform.header.stamp)
            try:
                stored = self.buffer.set_transform(
                    parent, child, stamp, transform_from_msg(transform.transform), static=static
                )
            except ValueError as exc:  # a frame its own parent: bad data from one publisher
                self.context.logger.warning(f"transform ignored: {exc}")
                continue
            if not stored:
                self.old_data += 1
                self._old_data_log.event(
                    1,
                    f"{parent} -> {child} at {stamp / 1e9:.3f} s is older than what the link holds: time went back "
                    "without the node's clock (a bag replayed without use_sim_time?) or an earlier sample was dated "
                    "in the future",
                )
