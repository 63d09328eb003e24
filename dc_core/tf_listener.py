"""Fill a :class:`dc_core.tf.TransformBuffer` from ``/tf`` and ``/tf_static``, as tf2_ros' listener does.

``/tf_static`` is read with TRANSIENT_LOCAL durability, so the statics a robot published before DC
started still arrive. ``/tf`` is read best effort, which matches reliable and best-effort
publishers alike. When the stamps jump backwards (a bag restarted with ``--loop``, a simulator
reset) the dynamic history is cleared, as tf2_ros does on a ROS time jump: interpolating between
two runs would invent a path.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from dc_core.plugin import PluginContext
from dc_core.rostime import stamp_ns
from dc_core.tf import Transform, TransformBuffer

TF_TOPIC = "/tf"
TF_STATIC_TOPIC = "/tf_static"
TF_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)
TF_STATIC_QOS = QoSProfile(
    depth=100, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL
)
# A stamp this far behind the newest one seen means time restarted, not a late message.
TIME_JUMP_BACK_NS = 1_000_000_000


def transform_from_msg(msg: Any) -> Transform:
    """A geometry_msgs/Transform as a :class:`Transform`."""
    t, r = msg.translation, msg.rotation
    return Transform((t.x, t.y, t.z), (r.x, r.y, r.z, r.w))


class TfListener:
    """Subscriptions of one plugin to /tf and /tf_static, feeding ``buffer``."""

    def __init__(
        self, context: PluginContext, buffer: TransformBuffer, on_update: Callable[[], None] | None = None
    ) -> None:
        self.context = context
        self.buffer = buffer
        # Called after each /tf message was added (on the thread that takes messages).
        self.on_update = on_update
        self.newest_ns = 0
        self.time_jumps = 0
        self._subscriptions: list[Any] = []

    def start(self) -> None:
        from tf2_msgs.msg import TFMessage

        self.stop()
        self._subscriptions = [
            self.context.subscribe(TFMessage, TF_TOPIC, self._on_tf, TF_QOS),
            self.context.subscribe(TFMessage, TF_STATIC_TOPIC, self._on_tf_static, TF_STATIC_QOS),
        ]

    def stop(self) -> None:
        for subscription in self._subscriptions:
            self.context.unsubscribe(subscription)
        self._subscriptions = []

    def _on_tf(self, message: Any, info: Any = None) -> None:
        self._add(message, static=False)
        if self.on_update is not None:
            self.on_update()

    def _on_tf_static(self, message: Any, info: Any = None) -> None:
        self._add(message, static=True)

    def _add(self, message: Any, *, static: bool) -> None:
        for transform in message.transforms:
            stamp = stamp_ns(transform.header.stamp)
            if not static:
                if stamp < self.newest_ns - TIME_JUMP_BACK_NS:
                    self.time_jumps += 1
                    self.context.logger.warning(
                        f"/tf time jumped back {(self.newest_ns - stamp) / 1e9:.1f} s: transform history cleared"
                    )
                    self.buffer.clear()
                    self.newest_ns = stamp
                self.newest_ns = max(self.newest_ns, stamp)
            try:
                self.buffer.set_transform(
                    transform.header.frame_id,
                    transform.child_frame_id,
                    stamp,
                    transform_from_msg(transform.transform),
                    static=static,
                )
            except ValueError as exc:  # a frame its own parent: bad data from one publisher
                self.context.logger.warning(f"transform ignored: {exc}")
