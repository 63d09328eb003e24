"""only_when's conditions through ROS: destination_server reads dc/condition/<name> as measurement_server
publishes it (a Condition message, transient local), in another DDS participant."""

from __future__ import annotations

import json
import time
import uuid
from pathlib import Path

import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.lifecycle import TransitionCallbackReturn
from rclpy.qos import QoSProfile, ReliabilityPolicy

from dc_core.diagnostics import OK
from dc_core.qos import CONDITION_QOS
from dc_destinations.server import DestinationServer
from dc_interfaces.msg import Condition, StringStamped
from tests.test_destination_ros import Running, write_params

# The file destination waits for the condition "docked" (the key is added to the section "disk").
ONLY_WHEN = "      only_when:\n        conditions: [docked]\n"


def test_a_condition_on_its_topic_holds_and_releases_a_destination(tmp_path: Path) -> None:
    topic = f"/dc_test/records_{uuid.uuid4().hex[:8]}"
    params = write_params(tmp_path, topic)
    text = params.read_text().replace('      time_format: "iso8601"\n', '      time_format: "iso8601"\n' + ONLY_WHEN)
    params.write_text(text)
    rclpy.init()
    other = Context()
    rclpy.init(context=other)
    try:
        server = DestinationServer(str(params))
        executor = SingleThreadedExecutor()
        executor.add_node(server)
        node = rclpy.create_node(f"dc_test_condition_{uuid.uuid4().hex[:8]}", context=other)
        records = node.create_publisher(
            StringStamped, topic, QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        )
        docked = node.create_publisher(Condition, "dc/condition/docked", CONDITION_QOS)
        running = Running(server, executor, records, topic, tmp_path / "out" / "records.jsonl")
        try:
            assert server.trigger_configure() == TransitionCallbackReturn.SUCCESS
            assert server.trigger_activate() == TransitionCallbackReturn.SUCCESS
            running.wait_for_subscription()
            assert running.spin_until(lambda: docked.get_subscription_count() >= 1), "no subscription to the condition"
            running.publish(json.dumps({"n": 1, "tags": ["disk"]}))
            pipeline = server.pipeline
            assert pipeline is not None
            assert running.spin_until(lambda: pipeline.metrics()["disk"]["buffered"] == 1)
            assert pipeline.metrics()["disk"]["held"] == "held: condition docked not heard yet"
            server._destination_metrics = pipeline.metrics()  # what publish_diagnostics' worker hands over
            (status,) = [d for d in server.diagnostic_statuses() if d.name.endswith(": disk")]
            assert (status.level, status.message) == (OK, "held: condition docked not heard yet")
            assert running.lines() == []
            docked.publish(Condition(data=True))
            heard = time.monotonic()
            assert running.spin_until(lambda: len(running.lines()) == 1), "not released by the condition"
            assert time.monotonic() - heard < 1.0
            docked.publish(Condition(data=False))
            assert running.spin_until(lambda: pipeline.metrics()["disk"]["held"] == "held: condition docked is false")
        finally:
            if server.lifecycle_state in ("active", "inactive"):
                server.trigger_shutdown()
            executor.shutdown()
            server.destroy_node()
            node.destroy_node()
    finally:
        rclpy.shutdown(context=other)
        rclpy.shutdown()
