"""Quality of service of the topics DC subscribes to and publishes: records between DC's servers, sensors.

Reliable, with a transient-local history of ``RECORD_HISTORY_DEPTH`` records per topic: a server
that starts, or restarts, after a record was published still receives it from the publisher's
history (docs/delivery.md, "The hop between servers"). A subscriber that asks for a volatile
topic (any plain ROS 2 node) is compatible and simply gets no history.
"""

from __future__ import annotations

from collections.abc import Mapping

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

RECORD_HISTORY_DEPTH = 1000

# Sensor topics other nodes publish (odometry, velocity commands): best effort matches reliable and
# best-effort publishers alike. Real robots publish /odom best effort, teleop and Nav2 publish /cmd_vel
# reliable; a reliable subscription would miss the former. A lost message costs one sample.
SENSOR_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
# A condition's state on dc/condition/<name>: its last value kept for late subscribers (the
# destination server's only_when reads it from another process).
CONDITION_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


def record_qos(depth: int = RECORD_HISTORY_DEPTH) -> QoSProfile:
    """Publishers of records: reliable, transient-local history of ``depth`` records."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )


RECORD_QOS = record_qos()


# A transient-local subscription does not match a volatile publisher (any plain ROS 2 node, or
# `ros2 topic pub`), so subscriptions are volatile unless the topic is known to be published by a
# DC server of the same configuration (dc_core.topics.published_topics).
VOLATILE_RECORD_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=RECORD_HISTORY_DEPTH,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)


def subscription_qos(topic: str, internal_topics: Mapping[str, int]) -> QoSProfile:
    """Transient-local for topics DC's own servers publish (history after a restart), else volatile."""
    depth = internal_topics.get(topic)
    return VOLATILE_RECORD_QOS if depth is None else record_qos(depth)
