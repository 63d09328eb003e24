"""The group server node: subscribes to each group's inputs and publishes merged records.

configure parses the parameter file and creates the publishers, activate subscribes and starts the
timer that expires incomplete sets, deactivate unsubscribes and settles what is still pending,
cleanup releases the publishers. ``python -m dc_group.server PARAMS [--autostart]``.
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable
from typing import Any

from dc_core.handoff import HandoffSender, destination_inputs
from dc_core.handoff_marks import marks_folder
from dc_core.lifecycle import ManagedServer, run_server
from dc_core.qos import RECORD_HISTORY_DEPTH, VOLATILE_RECORD_QOS, record_qos
from dc_core.record_history import SizedRecordPublisher, history_metrics
from dc_core.records import MalformedRecord
from dc_group.config import NODE_NAME, GroupServerConfig, parse_group_server
from dc_group.merge import parse_input
from dc_group.metrics import group_prometheus_text
from dc_group.pipeline import GroupOutput, GroupPipeline
from dc_interfaces.msg import StringStamped

# Same profile as the measurement server's records: reliable, deep enough for bursts.
# Repeated malformed messages on one topic are logged at most this often (all are counted).
MALFORMED_LOG_PERIOD_S = 10.0


class GroupServer(ManagedServer):
    def __init__(self, params_file: str) -> None:
        super().__init__(NODE_NAME, params_file)
        self.config: GroupServerConfig | None = None
        self.pipelines: dict[str, GroupPipeline] = {}
        self.malformed: dict[str, int] = {}
        self._routes: dict[str, list[GroupPipeline]] = {}
        self._group_publishers: dict[str, SizedRecordPublisher] = {}
        self._publish_of: dict[str, Callable[[int, str, str], None]] = {}
        self.handoff: HandoffSender | None = None
        self._input_subscriptions: list[Any] = []
        self._expiry_timer: Any = None
        self._malformed_logged_at: dict[str, float] = {}
        self._zero_stamp_warned: set[str] = set()
        # The metrics HTTP thread reads what the executor's callbacks change.
        self._lock = threading.Lock()

    # -- transitions ---------------------------------------------------------------------------
    def configure_server(self) -> None:
        servers = self.read_params_file()
        namespace = self.get_namespace()
        config = parse_group_server(servers[NODE_NAME], NODE_NAME, namespace)
        self.apply_node_params(config.node, config.warnings)
        handoff = self.handoff = HandoffSender(
            self,
            config.node.handoff,
            destination_inputs(servers, namespace),
            marks=marks_folder(namespace, self.get_name()),
        )
        for group in config.groups:
            pipeline = GroupPipeline(group, self.get_logger())
            self.pipelines[group.name] = pipeline
            publisher = SizedRecordPublisher(
                group.output,
                self._record_writers(group.output),
                self.destroy_publisher,
                history_depth=RECORD_HISTORY_DEPTH,
                history_bytes=group.history_bytes,
                logger=self.get_logger(),
            )
            self._group_publishers[group.name] = publisher
            self._publish_of[group.name] = handoff.output(group.output, publisher)
            for topic in group.inputs:
                self._routes.setdefault(topic, []).append(pipeline)
            self.get_logger().info(
                f"group {group.name}: {', '.join(group.inputs)} -> {group.output} "
                f"(sync_delay {group.sync_delay:g} s, sync_timeout {group.sync_timeout:g} s, "
                f"on_sync_timeout {'emit_partial' if group.emit_partial else 'drop'})"
            )
        self.config = config

    def _record_writers(self, topic: str) -> Callable[[int], Any]:
        def create(depth: int) -> Any:
            return self.create_publisher(StringStamped, topic, record_qos(depth))

        return create

    def activate_server(self) -> None:
        for topic in self._routes:
            self._input_subscriptions.append(
                # Volatile: plain ROS 2 nodes can feed a group, and a restarted group server does not
                # regroup old records into duplicate groups (docs/group_server.md).
                self.create_subscription(StringStamped, topic, self._callback_for(topic), VOLATILE_RECORD_QOS)
            )
        timeouts = [p.group.sync_timeout for p in self.pipelines.values()]
        # A set times out at most a quarter of its timeout late, and never more than 0.5 s late.
        period = min(0.5, max(0.02, min(timeouts) / 4)) if timeouts else 0.5
        self._expiry_timer = self.create_steady_timer(period, self._expire)
        if self.handoff is not None:
            self.handoff.start()
        assert self.config is not None
        self.start_metrics_http(
            self.config.node, self.metrics_document, lambda: group_prometheus_text(self.metrics_document())
        )

    def deactivate_server(self) -> None:
        for subscription in self._input_subscriptions:
            self.destroy_subscription(subscription)
        self._input_subscriptions.clear()
        if self._expiry_timer is not None:
            self._expiry_timer.cancel()
            self.destroy_timer(self._expiry_timer)
            self._expiry_timer = None
        # No message can complete what is pending any more: settle it as on a timeout.
        with self._lock:
            for name, pipeline in self.pipelines.items():
                self._publish(name, pipeline.flush())
                self.get_logger().info(f"group {name}: {pipeline.stats()}")
        if self.handoff is not None:
            self.handoff.stop()
        self.stop_metrics_http()

    def cleanup_server(self) -> None:
        if self.handoff is not None:
            self.handoff.close()
            self.handoff = None
        for publisher in self._group_publishers.values():
            publisher.destroy()
        self._group_publishers.clear()
        self._publish_of.clear()
        self.pipelines.clear()
        self.malformed.clear()
        self._routes.clear()
        self.config = None

    # -- work ----------------------------------------------------------------------------------
    def _callback_for(self, topic: str) -> Callable[[Any], None]:
        def on_message(msg: Any) -> None:
            self._on_message(topic, msg)

        return on_message

    def _on_message(self, topic: str, msg: Any) -> None:
        with self._lock:
            self._take(topic, msg)

    def _take(self, topic: str, msg: Any) -> None:
        now = time.monotonic()
        try:
            record = parse_input(topic, msg.group_key, msg.data)
        except MalformedRecord as exc:
            self._count_malformed(topic, exc, now)
            return
        stamp_ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        if stamp_ns == 0:
            # Publishers that leave the header empty (`ros2 topic pub`) would never match real stamps.
            stamp_ns = self.get_clock().now().nanoseconds
            if topic not in self._zero_stamp_warned:
                self._zero_stamp_warned.add(topic)
                self.get_logger().warning(f"{topic}: messages without header.stamp are stamped on receipt")
        for pipeline in self._routes.get(topic, []):
            self._publish(pipeline.group.name, pipeline.offer(record, stamp_ns, now))

    def _expire(self) -> None:
        now = time.monotonic()
        with self._lock:
            for name, pipeline in self.pipelines.items():
                self._publish(name, pipeline.expire(now))

    def _publish(self, group_name: str, outputs: list[GroupOutput]) -> None:
        publish = self._publish_of.get(group_name)
        if publish is None:
            return
        for output in outputs:
            publish(output.stamp_ns, output.data, output.group_key)

    def _count_malformed(self, topic: str, exc: MalformedRecord, now: float) -> None:
        count = self.malformed.get(topic, 0) + 1
        self.malformed[topic] = count
        last = self._malformed_logged_at.get(topic)
        if last is None or now - last >= MALFORMED_LOG_PERIOD_S:
            self._malformed_logged_at[topic] = now
            self.get_logger().error(f"{exc}; message ignored ({count} malformed on {topic} so far)")

    def stats(self) -> dict[str, dict[str, int]]:
        with self._lock:
            return {name: pipeline.stats() for name, pipeline in self.pipelines.items()}

    # -- metrics over HTTP ---------------------------------------------------------------------
    def metrics_document(self) -> dict[str, Any]:
        """Per group its counters, per input topic the malformed messages; both since configure."""
        groups = self.stats()
        with self._lock:
            inputs = {topic: {"malformed": self.malformed.get(topic, 0)} for topic in self._routes}
        handoff = self.handoff
        return {
            "groups": groups,
            "inputs": inputs,
            "handoff": handoff.metrics() if handoff is not None else {},
            "history": history_metrics(list(self._group_publishers.values())),
        }


def main() -> int:
    return run_server(GroupServer)


if __name__ == "__main__":
    sys.exit(main())
