"""The plugins of docs/plugin_development.md run as printed: a newcomer copying them gets working code.

The guide's Python blocks are loaded as modules; the measurement receives real
sensor_msgs/BatteryState messages over ROS, the destination writes to a key-value HTTP server
started here on loopback.
"""

from __future__ import annotations

import http.server
import json
import re
import sys
import threading
import time
import types
import uuid
from collections.abc import Iterator
from typing import Any

import jsonschema
import pytest
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile
from sensor_msgs.msg import BatteryState

from dc_core.destination import OutgoingRecord, SendOutcome
from dc_core.testing import FakeContext, PluginHarness
from tests.bringup_util import REPO

GUIDE = (REPO / "docs" / "plugin_development.md").read_text()


def guide_module(first_line: str) -> types.ModuleType:
    """The guide's Python block that starts with ``first_line``, loaded as a module."""
    (source,) = [block for block in re.findall(r"```python\n(.*?)```", GUIDE, re.S) if block.startswith(first_line)]
    name = "dc_guide_" + first_line.strip("# ").split("/")[1]
    module = types.ModuleType(name)
    sys.modules[name] = module  # dataclasses look their module up there
    exec(compile(source, first_line, "exec"), module.__dict__)
    return module


def test_the_guide_measurement_reports_the_battery_state_it_received(ros_node: Node) -> None:
    battery_module = guide_module("# my_robot_dc/battery/__init__.py")
    (schema_text,) = re.findall(r"```json\n(.*?)```", GUIDE, re.S)
    topic = f"/battery_{uuid.uuid4().hex[:8]}"
    harness = PluginHarness(ros_node)
    battery = harness.start(battery_module.Battery, {"topic": topic, "low_percent": 15.0})
    executor = SingleThreadedExecutor()
    executor.add_node(ros_node)
    publisher = ros_node.create_publisher(BatteryState, topic, QoSProfile(depth=10))
    try:
        assert battery.collect() is None, "nothing received yet: nothing to publish"
        state = BatteryState()
        state.percentage, state.voltage = 0.1, 11.5
        deadline = time.monotonic() + 10.0
        sample = None
        while sample is None and time.monotonic() < deadline:
            publisher.publish(state)
            executor.spin_once(timeout_sec=0.05)
            sample = battery.collect()
        assert sample == {"percent": 10.0, "voltage": pytest.approx(11.5), "low": True}
        jsonschema.validate(sample, json.loads(schema_text))
    finally:
        harness.stop(battery)
        executor.shutdown()


class _KeyValueServer(http.server.ThreadingHTTPServer):
    def __init__(self) -> None:
        super().__init__(("127.0.0.1", 0), _KeyValueHandler)
        self.store: dict[str, Any] = {}
        self.refuse: set[str] = set()
        self.authorization: list[str | None] = []


class _KeyValueHandler(http.server.BaseHTTPRequestHandler):
    server: _KeyValueServer

    def do_PUT(self) -> None:
        key = self.path.rsplit("/", 1)[-1]
        body = self.rfile.read(int(self.headers["Content-Length"]))
        self.server.authorization.append(self.headers.get("Authorization"))
        if key in self.server.refuse:
            self.send_response(400)
        else:
            self.server.store[key] = json.loads(body)
            self.send_response(200)
        self.send_header("Content-Length", "0")
        self.end_headers()

    def log_message(self, *args: object) -> None:
        pass


@pytest.fixture
def kv_server() -> Iterator[_KeyValueServer]:
    server = _KeyValueServer()
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        yield server
    finally:
        server.shutdown()
        server.server_close()


def test_the_guide_destination_stores_records_and_says_which_it_could_not(kv_server: _KeyValueServer) -> None:
    kv_module = guide_module("# my_robot_dc/kv/__init__.py")
    url = f"http://127.0.0.1:{kv_server.server_address[1]}/v1/kv/robot"
    harness = PluginHarness()
    kv = harness.start(kv_module.Kv, {"url": url, "token": "s3cret"})
    records = [OutgoingRecord(f"id-{n}", "/dc/measurement/battery", n, {"percent": n}) for n in range(3)]
    assert kv.send(records) is None
    assert kv_server.store == {f"id-{n}": {"percent": n} for n in range(3)}
    assert set(kv_server.authorization) == {"Bearer s3cret"}

    kv_server.refuse.add("id-1")
    outcome = kv.send(records)
    assert isinstance(outcome, SendOutcome) and outcome.reject == {1: "HTTP 400"} and not outcome.retry
    assert all("s3cret" not in line for _, line in harness.context(kv).logger.lines)
    harness.stop(kv)
    kv_server.shutdown()
    kv_server.server_close()
    with pytest.raises(kv_module.RetryableError):
        kv.send(records[:1])


def test_fake_context_needs_a_node_for_subscriptions() -> None:
    with pytest.raises(RuntimeError, match="needs a ROS node"):
        FakeContext().subscribe(BatteryState, "/x", lambda message, info: None, QoSProfile(depth=1))
