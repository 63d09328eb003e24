"""measurement_server as a real lifecycle node, driven transition by transition in this process.

The server runs in rclpy's default context (fresh per test); the test's own node, which listens
to the server's records and publishes its inputs, lives in a second context: its own DDS
participant, as another process' node would be.
"""

from __future__ import annotations

import itertools
import json
import re
import textwrap
import threading
import time
import urllib.error
import urllib.request
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from importlib.metadata import EntryPoint
from pathlib import Path
from typing import Any

import pytest
import rclpy
import yaml
from dc_lifecycle_interfaces.msg import Heartbeat
from diagnostic_msgs.msg import DiagnosticStatus
from rclpy.context import Context
from rclpy.duration import Duration
from rclpy.executors import SingleThreadedExecutor
from rclpy.lifecycle import TransitionCallbackReturn
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy

from dc_core import plugins
from dc_core.lifecycle import HEARTBEAT_QOS, HEARTBEAT_TOPIC, ServerLoop
from dc_core.measurement import Measurement
from dc_core.params import NoParams
from dc_core.qos import record_qos
from dc_core.worker import Outcome, Worker
from dc_interfaces.msg import StringStamped
from dc_measurements.config import parse_measurement_server
from dc_measurements.server import MeasurementServer
from tests.hostile_records import hostile_stream

DEADLINE_S = 15.0
RELIABLE = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
# The server's record writers are transient-local: a listener of the same durability gets what was
# published before its writer had matched it (discovery is not symmetric: the listener can see the
# writer before the writer sees the listener, and a volatile one then misses the first records).
RECORD_LISTENER = record_qos(1000)
SUCCESS = TransitionCallbackReturn.SUCCESS
FAILURE = TransitionCallbackReturn.FAILURE
REPO = Path(__file__).resolve().parent.parent
DOCS = REPO / "docs" / "plugins" / "measurements"


@dataclass
class Harness:
    tmp_path: Path
    peer: Node
    peer_executor: SingleThreadedExecutor
    server_executor: SingleThreadedExecutor
    server: MeasurementServer | None = None
    server_loop: ServerLoop | None = None
    received: dict[str, list[Any]] = field(default_factory=dict)

    def start_server(self, measurement_server_yaml: str) -> MeasurementServer:
        params = self.tmp_path / "params.yaml"
        params.write_text(measurement_server_yaml)
        self.server = MeasurementServer(str(params))
        self.server_executor.add_node(self.server)
        # The loop dc-bringup's server processes run: the executor, and the intake for records.
        self.server_loop = ServerLoop(self.server_executor, self.server.intake)
        return self.server

    def spin_once(self) -> None:
        if self.server_loop is not None:
            self.server_loop.spin_once(timeout_sec=0.01)
        self.peer_executor.spin_once(timeout_sec=0.01)

    def spin_until(self, done: Callable[[], bool], what: str, timeout: float = DEADLINE_S) -> None:
        deadline = time.monotonic() + timeout
        while not done():
            assert time.monotonic() < deadline, f"timed out after {timeout} s waiting for {what}"
            self.spin_once()

    def spin_for(self, seconds: float) -> None:
        """Keep both nodes running for a while: to show that something does *not* happen."""
        until = time.monotonic() + seconds
        while time.monotonic() < until:
            self.spin_once()

    def listen(self, topic: str) -> list[Any]:
        """Every StringStamped received on ``topic`` (the list fills while spinning)."""
        messages = self.received.setdefault(topic, [])
        self.peer.create_subscription(StringStamped, topic, messages.append, RECORD_LISTENER)
        return messages

    def wait_publisher(self, topic: str) -> None:
        subscription = next(s for s in self.peer.subscriptions if s.topic_name == topic)
        self.spin_until(lambda: subscription.get_publisher_count() >= 1, f"the server's publisher on {topic}")

    def input_publisher(self, topic: str) -> Any:
        """A publisher on ``topic``, returned once the server's subscription has matched it."""
        publisher = self.peer.create_publisher(StringStamped, topic, RELIABLE)
        self.spin_until(lambda: publisher.get_subscription_count() >= 1, f"the server to subscribe to {topic}")
        return publisher


@pytest.fixture
def harness(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Harness]:
    monkeypatch.setenv("HOME", str(tmp_path))  # the run id counter file stays in the test
    rclpy.init()  # the server's node uses the default context
    peer_context = Context()
    rclpy.init(context=peer_context)
    try:
        peer = rclpy.create_node(f"dc_test_peer_{uuid.uuid4().hex[:8]}", context=peer_context)
        peer_executor = SingleThreadedExecutor(context=peer_context)
        peer_executor.add_node(peer)
        h = Harness(tmp_path, peer, peer_executor, SingleThreadedExecutor())
        try:
            yield h
        finally:
            if h.server is not None:
                if h.server.lifecycle_state in ("active", "inactive"):
                    h.server.trigger_shutdown()
                h.server_executor.shutdown()
                h.server.destroy_node()
            peer_executor.shutdown()
            peer.destroy_node()
    finally:
        rclpy.shutdown(context=peer_context)
        rclpy.shutdown()


def unique(prefix: str) -> str:
    return f"{prefix}_{uuid.uuid4().hex[:8]}"


def records(messages: list[Any]) -> list[dict[str, Any]]:
    return [json.loads(m.data) for m in messages]


def more_than(messages: list[Any], count: int) -> Callable[[], bool]:
    return lambda: len(messages) > count


def uptime_params(name: str, polling_interval: int, init_collect: bool) -> str:
    return f"""
measurement_server:
  ros__parameters:
    measurement_plugins: ["{name}"]
    {name}:
      plugin: "dc_measurements/Uptime"
      polling_interval: {polling_interval}
      init_collect: {str(init_collect).lower()}
"""


# --- lifecycle -----------------------------------------------------------------------------------


def test_timers_start_on_activate_stop_on_deactivate_and_start_again_on_reactivate(harness: Harness) -> None:
    name = unique("uptime")
    server = harness.start_server(uptime_params(name, 100, init_collect=False))
    received = harness.listen(f"/dc/measurement/{name}")
    assert server.trigger_configure() == SUCCESS
    harness.wait_publisher(f"/dc/measurement/{name}")
    runner = server.runners[name]

    harness.spin_for(0.5)
    assert runner.stats.collected == 0, "configured but inactive: no timer runs yet"
    assert received == []

    assert server.trigger_activate() == SUCCESS
    harness.spin_until(lambda: len(received) >= 3, "records after activate")

    assert server.trigger_deactivate() == SUCCESS
    harness.spin_for(0.3)  # what was already on its way arrives
    collected, delivered = runner.stats.collected, len(received)
    harness.spin_for(1.0)  # ten polling intervals
    assert runner.stats.collected == collected, "collect() must not run while inactive"
    assert len(received) == delivered, "no record while inactive"

    # The original never published again after a pause: here the timers start again.
    assert server.trigger_activate() == SUCCESS
    harness.spin_until(lambda: len(received) >= delivered + 3, "records after re-activate")
    assert runner.stats.collected > collected


def test_cleanup_and_configure_again_restarts_collection(harness: Harness) -> None:
    name = unique("uptime")
    server = harness.start_server(uptime_params(name, 100, init_collect=True))
    received = harness.listen(f"/dc/measurement/{name}")
    for cycle in (1, 2):
        assert server.trigger_configure() == SUCCESS
        assert server.trigger_activate() == SUCCESS
        harness.spin_until(more_than(received, len(received) + 1), f"records in cycle {cycle}")
        assert server.trigger_deactivate() == SUCCESS
        assert server.trigger_cleanup() == SUCCESS
    # Each configure is a new run: the counter file was incremented twice.
    run_ids = [r["run_id"] for r in records(received)]
    assert run_ids[0] == "1" and run_ids[-1] == "2"


@pytest.mark.parametrize("init_collect", [True, False])
def test_init_collect_publishes_at_once(harness: Harness, init_collect: bool) -> None:
    name = unique("uptime")
    server = harness.start_server(uptime_params(name, 10_000, init_collect=init_collect))
    received = harness.listen(f"/dc/measurement/{name}")
    assert server.trigger_configure() == SUCCESS
    harness.wait_publisher(f"/dc/measurement/{name}")
    activated = time.monotonic()
    assert server.trigger_activate() == SUCCESS
    if init_collect:
        # The first polling interval ends after 10 s: this record is the one collected at activation.
        harness.spin_until(lambda: len(received) == 1, "the record collected at activation", timeout=3.0)
        assert time.monotonic() - activated < 3.0
        assert isinstance(records(received)[0]["time"], int)
    else:
        harness.spin_for(1.5)
        assert received == [] and server.runners[name].stats.collected == 0


# --- a failing configure -------------------------------------------------------------------------


def test_unreadable_value_from_file_fails_configure_clearly_then_configure_succeeds(
    harness: Harness, capfd: pytest.CaptureFixture[str]
) -> None:
    name = unique("uptime")
    robot_file = harness.tmp_path / "robot_name"
    server = harness.start_server(
        uptime_params(name, 100, init_collect=True)
        + f"""
    custom_str_params_list: ["robot_name"]
    custom_str_params:
      robot_name:
        name: "robot_name"
        value_from_file: "{robot_file}"
"""
    )
    received = harness.listen(f"/dc/measurement/{name}")
    assert server.trigger_configure() == FAILURE
    assert server.lifecycle_state == "unconfigured"
    log = capfd.readouterr().err
    assert re.search(
        rf"configure failed: measurement_server\.custom_str_params\.robot_name\.value_from_file: "
        rf"cannot read {re.escape(str(robot_file))}: No such file or directory",
        log,
    ), log

    robot_file.write_text("C3PO\n")
    assert server.trigger_configure() == SUCCESS
    assert server.trigger_activate() == SUCCESS
    harness.spin_until(lambda: len(received) >= 1, "a record after the second configure")
    assert records(received)[0]["robot_name"] == "C3PO"


def test_configure_failing_after_a_publisher_was_made_undoes_it(
    harness: Harness, capfd: pytest.CaptureFixture[str]
) -> None:
    first, second = unique("first"), unique("second")
    schema = harness.tmp_path / "schema.json"
    server = harness.start_server(f"""
measurement_server:
  ros__parameters:
    measurement_plugins: ["{first}", "{second}"]
    {first}:
      plugin: "dc_measurements/Uptime"
      polling_interval: 100
    {second}:
      plugin: "dc_measurements/Dummy"
      polling_interval: 100
      json_schema_path: "{schema}"
""")
    received = harness.listen(f"/dc/measurement/{first}")
    assert server.trigger_configure() == FAILURE
    assert f"cannot read JSON schema '{schema}'" in capfd.readouterr().err
    assert server.runners == {} and server.conditions == {}

    schema.write_text('{"type": "object", "required": ["message"]}')
    assert server.trigger_configure() == SUCCESS
    subscription = next(s for s in harness.peer.subscriptions if s.topic_name == f"/dc/measurement/{first}")
    harness.spin_until(lambda: subscription.get_publisher_count() >= 1, "the publisher")
    harness.spin_for(0.3)
    assert subscription.get_publisher_count() == 1, "the publisher of the failed configure was destroyed"
    assert server.trigger_activate() == SUCCESS
    harness.spin_until(lambda: len(received) >= 2, "records")


# --- event-driven StringStamped ------------------------------------------------------------------


@dataclass
class ActiveStringStamped:
    """An active StringStamped measurement: the test publishes on ``publisher`` and reads ``received``."""

    name: str
    topic: str
    plugin: Any
    publisher: Any
    received: list[Any]


def start_string_stamped(
    harness: Harness, timer_based: bool, qos_depth: int = 100, server_params: str = ""
) -> ActiveStringStamped:
    name, topic = unique("events"), f"/{unique('robot_events')}"
    server = harness.start_server(f"""
measurement_server:
  ros__parameters:
    {server_params}
    measurement_plugins: ["{name}"]
    {name}:
      plugin: "dc_measurements/StringStamped"
      topic: "{topic}"
      timer_based: {str(timer_based).lower()}
      qos_depth: {qos_depth}
      polling_interval: 100
      group_key: "configured_key"
""")
    received = harness.listen(f"/dc/measurement/{name}")
    assert server.trigger_configure() == SUCCESS
    harness.wait_publisher(f"/dc/measurement/{name}")
    assert server.trigger_activate() == SUCCESS
    publisher = harness.input_publisher(topic)
    return ActiveStringStamped(name, topic, server.runners[name].plugin, publisher, received)


def stamped(data: str, sec: int = 0, nanosec: int = 0, group_key: str = "") -> StringStamped:
    msg = StringStamped()
    msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
    msg.data = data
    msg.group_key = group_key
    return msg


def test_event_driven_string_stamped_publishes_each_record_once_with_its_stamp_and_group_key(
    harness: Harness,
) -> None:
    measurement = start_string_stamped(harness, timer_based=False)
    publisher, received = measurement.publisher, measurement.received
    assert harness.server is not None and harness.server.intake.active, "records are taken by the server's intake"

    for seq in range(5):
        # The last one has no group key of its own: the configured one applies.
        publisher.publish(
            stamped(json.dumps({"seq": seq}), 1_700_000_000 + seq, 1_000 * seq, "source_key" if seq < 4 else "")
        )
    harness.spin_until(lambda: len(received) >= 5, "the five records")
    # Ten polling intervals more: the original re-published the latest record at each of them.
    harness.spin_for(1.0)
    assert [r["seq"] for r in records(received)] == [0, 1, 2, 3, 4]
    assert [(m.header.stamp.sec, m.header.stamp.nanosec) for m in received] == [
        (1_700_000_000 + seq, 1_000 * seq) for seq in range(5)
    ]
    assert [m.group_key for m in received] == ["source_key"] * 4 + ["configured_key"]
    assert all(r["name"] == measurement.name for r in records(received))


def start_event_driven(harness: Harness, name: str, topic: str, more: str = "") -> MeasurementServer:
    """A server (not configured yet) with one event-driven StringStamped measurement, ``more`` its last parameter line."""
    return harness.start_server(f"""
measurement_server:
  ros__parameters:
    measurement_plugins: ["{name}"]
    {name}:
      plugin: "dc_measurements/StringStamped"
      topic: "{topic}"
      timer_based: false
      {more}
""")


def test_records_that_reach_an_inactive_server_are_published_once_it_is_active(harness: Harness) -> None:
    """Between configure and activate, and while deactivated, DDS still delivers your node's records to
    measurement_server (and tells your node they arrived): they are published at activation, in order."""
    name, topic = unique("events"), f"/{unique('robot_events')}"
    server = start_event_driven(harness, name, topic)
    received = harness.listen(f"/dc/measurement/{name}")
    assert server.trigger_configure() == SUCCESS
    harness.wait_publisher(f"/dc/measurement/{name}")
    publisher = harness.input_publisher(topic)
    for seq in range(3):
        publisher.publish(stamped(json.dumps({"seq": seq})))
    harness.spin_until(lambda: server.held_while_inactive == 3, "the server to take the records while inactive")
    assert server.trigger_activate() == SUCCESS
    harness.spin_until(more_than(received, 2), "the records taken before activation")

    assert server.trigger_deactivate() == SUCCESS
    for seq in range(3, 5):
        publisher.publish(stamped(json.dumps({"seq": seq})))
    harness.spin_until(lambda: server.held_while_inactive == 5, "the server to take the records while deactivated")
    assert server.trigger_activate() == SUCCESS
    publisher.publish(stamped(json.dumps({"seq": 5})))
    harness.spin_until(more_than(received, 5), "every record")
    assert [r["seq"] for r in records(received)] == [0, 1, 2, 3, 4, 5]


def test_a_latched_state_published_before_the_server_subscribed_is_forwarded_with_transient_local(
    harness: Harness,
) -> None:
    """destination_server latches its destinations' health on dc/destination_health, and a robot's
    first state is often published before measurement_server starts: the fleet page must get it."""
    from dc_destinations.health import HEALTH_QOS

    topic, name = f"/{unique('destination_health')}", unique("destination_health")
    latched = harness.peer.create_publisher(StringStamped, topic, HEALTH_QOS)
    latched.publish(stamped(json.dumps({"pg": {"state": "failing", "reason": "connection refused"}}), 1_700_000_000))
    server = start_event_driven(harness, name, topic, "transient_local: true")
    received = harness.listen(f"/dc/measurement/{name}")
    assert server.trigger_configure() == SUCCESS
    harness.wait_publisher(f"/dc/measurement/{name}")
    assert server.trigger_activate() == SUCCESS
    harness.spin_until(lambda: len(received) >= 1, "the state published before the server subscribed")
    assert records(received)[0]["pg"]["state"] == "failing"
    assert received[0].header.stamp.sec == 1_700_000_000
    # The next change, as it comes; and after a deactivation, the state then current again.
    latched.publish(stamped(json.dumps({"pg": {"state": "ok"}}), 1_700_000_001))
    harness.spin_until(lambda: len(received) >= 2, "the next state")
    assert server.trigger_deactivate() == SUCCESS
    assert server.trigger_activate() == SUCCESS
    harness.spin_until(lambda: len(received) >= 3, "the current state at the next activation")
    assert [r["pg"]["state"] for r in records(received)] == ["failing", "ok", "ok"]


@pytest.mark.parametrize("timer_based", [False, True], ids=["event-driven", "timer-based"])
def test_malformed_input_is_logged_and_counted_and_the_next_record_passes(
    harness: Harness, capfd: pytest.CaptureFixture[str], timer_based: bool
) -> None:
    measurement = start_string_stamped(harness, timer_based=timer_based)
    plugin, topic = measurement.plugin, measurement.topic

    measurement.publisher.publish(stamped('{"seq": 1,'))
    harness.spin_until(lambda: plugin.malformed == 1, "the first malformed record")
    measurement.publisher.publish(stamped("[1, 2]"))
    harness.spin_until(lambda: plugin.malformed == 2, "the second malformed record")
    measurement.publisher.publish(stamped('{"seq": 2}', 1_700_000_000))
    harness.spin_until(lambda: len(measurement.received) >= 1, "the valid record")
    assert [r["seq"] for r in records(measurement.received)] == [2]
    log = capfd.readouterr().err
    assert f"malformed records on {topic} not published: 1 (invalid JSON" in log and "'{\"seq\": 1,'" in log, log
    assert f"malformed records on {topic} not published: 1 (expected a JSON object, got a JSON array" in log, log


def test_hostile_input_is_counted_as_malformed_and_every_valid_record_is_published_once(harness: Harness) -> None:
    stream = hostile_stream(valid=500, hostile=1500, tags=["file"], seed=11)
    measurement = start_string_stamped(harness, timer_based=False, qos_depth=1000)
    plugin, received = measurement.plugin, measurement.received
    runner = harness.server.runners[measurement.name] if harness.server else None
    assert runner is not None
    for start in range(0, len(stream), 200):
        for item in stream[start : start + 200]:
            measurement.publisher.publish(stamped(item.text, 1_700_000_000))
        taken = min(start + 200, len(stream))

        def chunk_taken(taken: int = taken) -> bool:
            return bool(plugin.malformed + runner.stats.collected >= taken)

        harness.spin_until(chunk_taken, "the chunk")
        # And read by this test before the next chunk: its own queue (depth 1000) must not overflow.
        valid_so_far = sum(not item.malformed for item in stream[:taken])

        def chunk_read(valid_so_far: int = valid_so_far) -> bool:
            return len(received) >= valid_so_far

        harness.spin_until(chunk_read, "the chunk's valid records")

    valid = [item for item in stream if not item.malformed]
    published = records(received)
    assert sorted(r["n"] for r in published if "n" in r) == list(range(500))
    assert sorted(r["odd"] for r in published if "odd" in r) == sorted(i.odd for i in valid if i.odd is not None)
    assert plugin.malformed == sum(item.malformed for item in stream)
    assert runner.stats.errors == 0 and plugin.lost == 0


def test_timer_based_counts_and_logs_once_the_records_a_newer_one_replaced(
    harness: Harness, capfd: pytest.CaptureFixture[str]
) -> None:
    measurement = start_string_stamped(harness, timer_based=True)
    plugin, received = measurement.plugin, measurement.received
    for seq in range(50):  # a burst between two polls (polling_interval 100 ms)
        measurement.publisher.publish(stamped(json.dumps({"seq": seq}), 1_700_000_000 + seq))
    harness.spin_until(lambda: plugin.replaced + len(received) == 50, "every record published or replaced")
    assert plugin.replaced > 0
    assert records(received)[-1]["seq"] == 49, "the latest record is the one a poll publishes"
    assert harness.server is not None
    assert harness.server.metrics_document()["measurements"][measurement.name]["replaced"] == plugin.replaced
    log = capfd.readouterr().err
    assert log.count("replaced by a newer one before a poll published them") == 1, log


def test_records_overwritten_in_the_input_queue_are_counted_and_logged(
    harness: Harness, capfd: pytest.CaptureFixture[str]
) -> None:
    measurement = start_string_stamped(harness, timer_based=False, qos_depth=5)
    publisher, received = measurement.publisher, measurement.received

    publisher.publish(stamped('{"n": 0}'))
    harness.spin_until(lambda: len(received) == 1, "the first record")
    # 50 more while the server's executor does not run: its queue of 5 keeps the last five.
    for n in range(1, 51):
        publisher.publish(stamped(json.dumps({"n": n})))
    assert publisher.wait_for_all_acked(Duration(seconds=DEADLINE_S))
    harness.spin_until(lambda: len(received) == 6, "the five records the queue kept")

    assert [r["n"] for r in records(received)] == [0, 46, 47, 48, 49, 50]
    assert measurement.plugin.lost == 45
    log = capfd.readouterr().err
    # Record n is the publisher's sample n + 1.
    assert (
        f"measurement {measurement.name}: records lost before measurement_server: 45 ({measurement.topic}:"
        " publication sequence numbers"
        " 2..46 never arrived; the queues, qos_depth 5 and the publisher's depth, overflowed)"
    ) in log, log


def test_counters_are_served_over_http_while_active(harness: Harness) -> None:
    measurement = start_string_stamped(harness, timer_based=False, server_params="http_server: true\n    http_port: 0")
    assert harness.server is not None and harness.server.http_address is not None
    host, port = harness.server.http_address
    assert host == "127.0.0.1"
    base = f"http://{host}:{port}/api/v1"
    measurement.publisher.publish(stamped("[1, 2]"))
    measurement.publisher.publish(stamped('{"seq": 1}'))
    harness.spin_until(lambda: len(measurement.received) == 1, "the valid record")

    with urllib.request.urlopen(f"{base}/metrics", timeout=5) as reply:
        document = json.load(reply)
    history = document.pop("history")[f"/dc/measurement/{measurement.name}"]
    assert (history["depth"], history["replaced"]) == (1000, 0)  # small records: the count bounds the history
    assert history["held_bytes"] == history["largest_record"] > 0  # the one record published
    assert document == {
        "measurements": {
            measurement.name: {
                "collected": 1,
                "published": 1,
                "empty": 0,
                "invalid": 0,
                "gated": 0,
                "errors": 0,
                "overrun": 0,
                "malformed": 1,
                "lost": 0,
                "replaced": 0,
            }
        },
        "metrics_http": {"refused_connections": 0},  # the HTTP server's own (dc_core.http_status)
        "threads": {"thread_failures": 0, "unhealthy": ""},
        "handoff": {},  # no destination_server reads the topic: nothing is kept for one
    }
    with urllib.request.urlopen(f"{base}/metrics/prometheus", timeout=5) as reply:
        lines = reply.read().decode().splitlines()
    assert "dc_thread_failures_total 0" in lines
    assert f'dc_measurement_published_total{{measurement="{measurement.name}"}} 1' in lines
    assert f'dc_measurement_malformed_total{{measurement="{measurement.name}"}} 1' in lines
    with urllib.request.urlopen(f"{base}/health", timeout=5) as reply:
        assert json.load(reply) == {"status": "ok"}

    assert harness.server.trigger_deactivate() == SUCCESS
    assert harness.server.http_address is None
    with pytest.raises(urllib.error.URLError):
        urllib.request.urlopen(f"{base}/health", timeout=5)


def test_each_measurement_has_a_diagnostic_status_warn_while_it_loses_records(harness: Harness) -> None:
    measurement = start_string_stamped(harness, timer_based=False)
    server = harness.server
    assert server is not None
    measurement.publisher.publish(stamped("[1, 2]"))
    measurement.publisher.publish(stamped('{"seq": 1}'))
    harness.spin_until(lambda: len(measurement.received) == 1, "the valid record")

    def status() -> tuple[bytes, str, dict[str, str]]:
        (found,) = [s for s in server.diagnostic_statuses() if s.name == f"measurement_server: {measurement.name}"]
        return found.level, found.message, {kv.key: kv.value for kv in found.values}

    level, message, values = status()
    assert level == DiagnosticStatus.WARN and message.startswith("1 malformed since configure"), message
    assert (values["published"], values["malformed"]) == ("1", "1")
    measurement.publisher.publish(stamped('{"seq": 2}'))
    harness.spin_until(lambda: len(measurement.received) == 2, "the second record")
    level, message, values = status()  # what happened since the previous status: only a good record
    assert (level, message) == (DiagnosticStatus.OK, "publishing") and float(values["records_per_s"]) > 0
    level, message, _ = status()
    assert (level, message) == (DiagnosticStatus.OK, "idle: nothing collected since the previous status")
    assert server.trigger_deactivate() == SUCCESS
    assert [s.name for s in server.diagnostic_statuses()] == [], "only the server's own status while inactive"


# --- the doc pages' examples run -----------------------------------------------------------------


def doc_example(plugin_folder: str) -> tuple[str, dict[str, Any]]:
    text = (REPO / "dc_measurements" / plugin_folder / "README.md").read_text()
    config = re.findall(r"```yaml\n(.*?)```", text, re.S)[0]
    output = json.loads(re.findall(r"```json\n(.*?)```", text, re.S)[0])
    return config, output


@pytest.mark.parametrize("page", ["uptime", "dummy", "string_stamped"])
def test_doc_page_example_gives_the_documented_record(harness: Harness, page: str) -> None:
    config, documented = doc_example(page)
    server = harness.start_server(config)
    assert server.trigger_configure() == SUCCESS, config
    (name,) = server.runners
    topic = server.runners[name].config.output_topic
    received = harness.listen(topic)
    harness.wait_publisher(topic)
    assert server.trigger_activate() == SUCCESS
    if page == "string_stamped":
        plugin: Any = server.runners[name].plugin
        source = harness.input_publisher(plugin.params.topic.replace("-", "_"))
        payload = {k: v for k, v in documented.items() if k not in ("name", "run_id", "tags")}
        source.publish(stamped(json.dumps(payload), 1_700_000_000))
    harness.spin_until(lambda: len(received) >= 1, f"the record of {page}'s page")
    record = records(received)[0]
    assert set(record) == set(documented), record
    assert record["name"] == documented["name"]


def test_index_page_examples_are_valid_configurations(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("HOME", "/home/robot")
    text = (DOCS / "index.md").read_text()
    blocks = re.findall(r"```yaml\n(.*?)```", text, re.S)
    assert blocks
    for block in blocks:
        parse_measurement_server(yaml.safe_load(block)["measurement_server"]["ros__parameters"])


# --- slow collections on the worker ----------------------------------------------------------------
# A plugin that sleeps 2 s in collect() (as a camera saving JPEGs or a ping to a dead host would
# block) runs beside a 100 ms measurement in one server; the peer counts both outputs and the
# server's heartbeats.

SLEEP_S = 2.0


class SleepyMeasurement(Measurement[NoParams]):
    """Sleeps in collect(), as a collection waiting on a slow device does."""

    collect_in_worker = True

    def __init__(self, context: Any, params: Any) -> None:
        super().__init__(context, params)
        self.collections = 0
        self.threads: set[str] = set()

    def collect(self) -> dict[str, Any]:
        self.threads.add(threading.current_thread().name)
        time.sleep(SLEEP_S)
        self.collections += 1
        return {"collection": self.collections}


@pytest.fixture
def sleepy_plugin(monkeypatch: pytest.MonkeyPatch) -> None:
    original = plugins._entry_points
    entry = EntryPoint("test/Sleepy", f"{__name__}:SleepyMeasurement", "dc.measurements")

    def with_sleepy(kind: str) -> dict[str, EntryPoint]:
        found = original(kind)
        return {**found, entry.name: entry} if kind == "measurements" else found

    monkeypatch.setattr(plugins, "_entry_points", with_sleepy)


def gaps(times: list[float]) -> list[float]:
    return [b - a for a, b in itertools.pairwise(times)]


def run_beside_a_fast_measurement(
    harness: Harness, slow: str, slow_section: str
) -> tuple[MeasurementServer, list[Any]]:
    """Run measurement ``slow`` (its YAML section, polled every 500 ms) beside an Uptime polled every
    100 ms and a 0.2 s heartbeat until ``slow`` published twice; assert that its collections, 2 s each,
    left neither the fast measurement nor the heartbeat waiting (they would on the main thread). The
    server is left active; returns it and the records of ``slow``."""
    fast = unique("uptime")
    server = harness.start_server(f"""
measurement_server:
  ros__parameters:
    heartbeat_period: 0.2
    measurement_plugins: ["{slow}", "{fast}"]
    {slow}:
      polling_interval: 500
{textwrap.indent(textwrap.dedent(slow_section).strip(), "      ")}
    {fast}:
      plugin: "dc_measurements/Uptime"
      polling_interval: 100
""")
    slow_out = harness.listen(f"/dc/measurement/{slow}")
    fast_out = harness.listen(f"/dc/measurement/{fast}")
    fast_times: list[float] = []
    heartbeats: list[float] = []
    harness.peer.create_subscription(
        Heartbeat, HEARTBEAT_TOPIC, lambda msg: heartbeats.append(time.monotonic()), HEARTBEAT_QOS
    )
    assert server.trigger_configure() == SUCCESS
    harness.wait_publisher(f"/dc/measurement/{fast}")
    assert server.trigger_activate() == SUCCESS

    def fast_arrivals() -> bool:
        while len(fast_times) < len(fast_out):
            fast_times.append(time.monotonic())
        return len(slow_out) >= 2

    harness.spin_until(fast_arrivals, f"two records of {slow}", timeout=15.0)
    # 100 ms and 200 ms periods: a collection on the main thread would leave 2 s gaps in both.
    assert len(fast_times) >= 30
    assert max(gaps(fast_times)) < 1.0, gaps(fast_times)
    assert max(gaps(heartbeats)) < 1.0, gaps(heartbeats)
    # Polls that came while a collection ran were skipped, not queued behind it.
    assert server.runners[slow].stats.overrun >= 4
    assert server.metrics_document()["measurements"][slow]["overrun"] == server.runners[slow].stats.overrun
    return server, slow_out


def test_a_collection_sleeping_2_s_delays_neither_a_fast_measurement_nor_the_heartbeat(
    harness: Harness,
    sleepy_plugin: None,
) -> None:
    slow = unique("sleepy")
    server, slow_out = run_beside_a_fast_measurement(
        harness,
        slow,
        """
        plugin: "test/Sleepy"
        enable_validator: false
        """,
    )
    plugin = server.runners[slow].plugin
    assert isinstance(plugin, SleepyMeasurement)
    assert [r["collection"] for r in records(slow_out)] == [1, 2]
    assert all(name.startswith("measurement_server-worker") for name in plugin.threads), plugin.threads

    # Deactivate waits for the collection under way; nothing of it is published afterwards.
    assert server.trigger_deactivate() == SUCCESS
    published = len(slow_out)
    harness.spin_for(0.5)
    assert len(slow_out) == published


def test_a_tcp_health_connect_that_hangs_delays_neither_a_fast_measurement_nor_the_heartbeat(
    harness: Harness, silent_port: int
) -> None:
    """TCPHealth waits its 2 s timeout for a port that drops SYNs: on the worker, not the main loop."""
    health = unique("tcp_health")
    server, health_out = run_beside_a_fast_measurement(
        harness,
        health,
        f"""
        plugin: "dc_measurements/TCPHealth"
        name: "blackholed"
        port: {silent_port}
        timeout: 2000
        """,
    )
    assert [r["active"] for r in records(health_out)] == [False, False]
    assert server.trigger_deactivate() == SUCCESS


def test_worker_hands_outcomes_back_on_the_thread_that_runs_them() -> None:
    woken = threading.Event()
    worker = Worker("test-worker", woken.set, threads=2)
    outcomes: list[tuple[str, Any]] = []

    def fail() -> int:
        raise ValueError("broken device")

    try:
        worker.submit(lambda: 42, lambda o: outcomes.append((threading.current_thread().name, o.get())))
        worker.submit(fail, lambda o: outcomes.append(("error", o.error)))
        assert worker.wait_idle(5.0)
        assert woken.is_set()
        assert outcomes == [], "nothing runs before the main thread asks"
        assert worker.run_finished() == 2
        assert (threading.current_thread().name, 42) in outcomes
        (error,) = [o for kind, o in outcomes if kind == "error"]
        assert isinstance(error, ValueError)
        with pytest.raises(ValueError, match="broken device"):
            Outcome[int](error=ValueError("broken device")).get()
    finally:
        worker.shutdown()


# --- the history of the output topics, bounded in bytes ------------------------------------------


def test_a_large_record_measurement_gets_a_shallow_history_a_small_one_keeps_1000(harness: Harness) -> None:
    big, small = unique("big"), unique("small")
    blob = "x" * 100_000
    server = harness.start_server(f"""
measurement_server:
  ros__parameters:
    measurement_plugins: ["{big}", "{small}"]
    {big}:
      plugin: "dc_measurements/Dummy"
      polling_interval: 100
      history_bytes: 1048576
      record: '{{"blob": "{blob}"}}'
    {small}:
      plugin: "dc_measurements/Dummy"
      polling_interval: 100
      history_bytes: 1048576
""")
    # A volatile subscriber from the start (as group_server's): the writer's replacement loses it nothing.
    live = harness.listen(f"/dc/measurement/{big}")
    assert server.trigger_configure() == SUCCESS
    assert server.trigger_activate() == SUCCESS
    harness.spin_until(lambda: server.runners[big].stats.published >= 15, "15 large records")
    assert server.trigger_deactivate() == SUCCESS
    published = server.runners[big].stats.published
    harness.spin_until(lambda: len(live) == published, "every large record, live")
    history = server.metrics_document()["history"]
    size = history[f"/dc/measurement/{big}"]["largest_record"]
    assert size > 100_000
    assert history[f"/dc/measurement/{big}"]["depth"] == 1048576 // size == 10
    assert history[f"/dc/measurement/{big}"]["replaced"] == 1
    assert history[f"/dc/measurement/{small}"]["depth"] == 1000

    # What DDS replays to a transient-local subscriber that joins late: the newest 10, not all 15+.
    late: list[Any] = []
    harness.peer.create_subscription(StringStamped, f"/dc/measurement/{big}", late.append, record_qos(1000))
    harness.spin_until(lambda: len(late) >= 10, "the history")
    harness.spin_for(0.5)  # nothing beyond it
    assert len(late) == 10
    assert [m.data for m in late] == [m.data for m in live[-10:]]
