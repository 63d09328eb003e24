"""The group server node in-process with real rclpy: StringStamped in, merged StringStamped out.

``ManagedServer`` creates its node in the default context, so each test initialises the default
context and shuts it down afterwards (rclpy then starts the next test with a new one).
"""

from __future__ import annotations

import json
import socket
import time
import urllib.error
import urllib.request
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
import rclpy
import yaml
from rclpy.executors import SingleThreadedExecutor
from rclpy.lifecycle import TransitionCallbackReturn
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy

from dc_core.qos import record_qos
from dc_group.server import GroupServer
from dc_interfaces.msg import StringStamped
from tests.hostile_records import hostile_stream

DEADLINE_S = 10.0
QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
S = 1_000_000_000


@dataclass
class Received:
    data: dict[str, Any]
    stamp_ns: int
    group_key: str


@dataclass
class Harness:
    server: GroupServer
    helper: Node
    executor: SingleThreadedExecutor
    prefix: str
    publishers: dict[str, Any] = field(default_factory=dict)
    received: dict[str, list[Received]] = field(default_factory=dict)

    def topic(self, name: str) -> str:
        return f"{self.prefix}/{name}"

    def spin_until(self, done: Callable[[], bool], timeout: float = DEADLINE_S) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if done():
                return True
            self.executor.spin_once(timeout_sec=0.02)
        return done()

    def listen(self, name: str) -> list[Received]:
        sink: list[Received] = self.received.setdefault(name, [])

        def on_message(msg: Any) -> None:
            stamp = msg.header.stamp.sec * S + msg.header.stamp.nanosec
            sink.append(Received(json.loads(msg.data), stamp, msg.group_key))

        self.helper.create_subscription(StringStamped, self.topic(name), on_message, QOS)
        return sink

    def publish(self, name: str, record: dict[str, Any] | str, stamp_ns: int, group_key: str = "") -> None:
        publisher = self.publishers.get(name)
        if publisher is None:
            publisher = self.helper.create_publisher(StringStamped, self.topic(name), QOS)
            self.publishers[name] = publisher
            assert self.spin_until(lambda: publisher.get_subscription_count() > 0), f"no subscriber on {name}"
        msg = StringStamped()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, S)
        msg.data = record if isinstance(record, str) else json.dumps(record)
        msg.group_key = group_key
        publisher.publish(msg)

    def wait_for_output(self, name: str, count: int = 1) -> list[Received]:
        sink = self.received[name]
        assert self.spin_until(lambda: len(sink) >= count), f"{len(sink)} of {count} records on {name}"
        return sink

    def wait_matched(self, name: str) -> None:
        publisher = self.publishers[name]
        assert self.spin_until(lambda: publisher.get_subscription_count() > 0), f"no subscriber on {name}"


def write_params(
    tmp_path: Path, prefix: str, groups: dict[str, dict[str, Any]], server_params: dict[str, Any] | None = None
) -> Path:
    section: dict[str, Any] = {"groups": list(groups), **(server_params or {})}
    for name, body in groups.items():
        body = dict(body)
        body["inputs"] = [f"{prefix}/{t}" for t in body["inputs"]]
        body["output"] = f"{prefix}/{body.get('output', name)}"
        section[name] = body
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump({"group_server": {"ros__parameters": section}}))
    return path


@pytest.fixture
def start(tmp_path: Path) -> Iterator[Callable[[dict[str, dict[str, Any]]], Harness]]:
    rclpy.init()
    harnesses: list[Harness] = []

    def make(groups: dict[str, dict[str, Any]], **server_params: Any) -> Harness:
        prefix = f"/test_group_{uuid.uuid4().hex[:8]}"
        server = GroupServer(str(write_params(tmp_path, prefix, groups, server_params)))
        helper = rclpy.create_node(f"group_test_{uuid.uuid4().hex[:8]}")
        executor = SingleThreadedExecutor()
        executor.add_node(server)
        executor.add_node(helper)
        harness = Harness(server, helper, executor, prefix)
        harnesses.append(harness)
        return harness

    try:
        yield make
    finally:
        for harness in harnesses:
            harness.executor.shutdown()
            harness.helper.destroy_node()
            harness.server.destroy_node()
        rclpy.shutdown()


def activate(harness: Harness) -> None:
    assert harness.server.trigger_configure() == TransitionCallbackReturn.SUCCESS
    assert harness.server.trigger_activate() == TransitionCallbackReturn.SUCCESS


def test_merges_two_inputs_into_one_record_stamped_with_the_latest_input(start: Any) -> None:
    h = start({"memory_uptime": {"inputs": ["memory", "uptime"], "tags": ["flb_stdout"], "sync_delay": 1.0}})
    activate(h)
    out = h.listen("memory_uptime")
    h.publish("memory", {"used": 71.6, "tags": ["flb_stdout"]}, 100 * S, group_key="memory")
    h.publish("uptime", {"time": 96894, "tags": ["flb_stdout"]}, 100 * S + S // 4, group_key="uptime")
    (record,) = h.wait_for_output("memory_uptime")
    assert record.data == {
        "memory": {"used": 71.6},
        "uptime": {"time": 96894},
        "tags": ["flb_stdout"],
        "name": "memory_uptime",
    }
    assert record.stamp_ns == 100 * S + S // 4
    assert record.group_key == "memory_uptime"
    assert out == [record]


def test_malformed_json_is_counted_and_does_not_stop_the_group(start: Any) -> None:
    h = start({"g": {"inputs": ["a", "b"], "sync_delay": 0.5}})
    activate(h)
    h.listen("g")
    h.publish("a", "{this is not json", 5 * S)
    h.publish("a", "[1, 2, 3]", 5 * S)
    assert h.spin_until(lambda: h.server.malformed.get(h.topic("a")) == 2)
    h.publish("a", {"v": 1}, 6 * S)
    h.publish("b", {"w": 2}, 6 * S)
    (record,) = h.wait_for_output("g")
    assert record.data == {"a": {"v": 1}, "b": {"w": 2}, "name": "g"}
    assert h.server.lifecycle_state == "active"


def test_hostile_input_is_counted_as_malformed_and_every_valid_record_is_grouped_once(start: Any) -> None:
    h = start({"g": {"inputs": ["a"], "sync_delay": 0.1}})
    activate(h)
    out = h.listen("g")
    stream = hostile_stream(valid=500, hostile=1500, tags=["file"], seed=7)
    topic = h.topic("a")
    for start_at in range(0, len(stream), 100):
        chunk = stream[start_at : start_at + 100]
        for i, item in enumerate(chunk, start_at):
            h.publish("a", item.text, (i + 1) * S // 1000)  # one input: each valid record is a complete set
        taken = start_at + len(chunk)
        valid_so_far = sum(not item.malformed for item in stream[:taken])
        malformed_so_far = taken - valid_so_far
        assert h.spin_until(
            lambda m=malformed_so_far, v=valid_so_far: h.server.malformed.get(topic, 0) == m and len(out) == v
        ), f"{h.server.malformed.get(topic, 0)} malformed, {len(out)} grouped after {taken} inputs"
    grouped = [r.data["a"] for r in out]
    assert sorted(r["n"] for r in grouped if "n" in r) == list(range(500))
    valid_odd = sorted(item.odd for item in stream if item.odd is not None)
    assert sorted(r["odd"] for r in grouped if "odd" in r) == valid_odd
    assert h.server.malformed[topic] == sum(item.malformed for item in stream)
    assert h.server.lifecycle_state == "active"


def test_a_silent_input_gives_partial_records_after_the_timeout(start: Any) -> None:
    h = start(
        {
            "g": {
                "inputs": ["a", "b"],
                "sync_delay": 0.1,
                "sync_timeout": 0.3,
                "on_sync_timeout": "emit_partial",
            }
        }
    )
    activate(h)
    h.listen("g")
    h.publish("a", {"v": 1}, 7 * S)
    (record,) = h.wait_for_output("g")
    assert record.data == {"a": {"v": 1}, "missing_inputs": [h.topic("b")], "name": "g"}
    assert record.stamp_ns == 7 * S
    assert h.server.stats()["g"]["published_partial"] == 1


def test_a_silent_input_drops_sets_by_default_and_counts_them(start: Any) -> None:
    h = start({"g": {"inputs": ["a", "b"], "sync_delay": 0.1, "sync_timeout": 0.2}})
    activate(h)
    out = h.listen("g")
    h.publish("a", {"v": 1}, 7 * S)
    assert h.spin_until(lambda: h.server.stats()["g"]["dropped_incomplete"] == 1)
    assert out == []


def get(url: str) -> tuple[int, str]:
    try:
        with urllib.request.urlopen(url, timeout=5) as reply:
            return reply.status, reply.read().decode()
    except urllib.error.HTTPError as error:
        return error.code, error.read().decode()


def test_counters_are_served_over_http_while_active(start: Any) -> None:
    h = start(
        {"pair": {"inputs": ["a", "b"], "sync_delay": 0.1, "sync_timeout": 0.2}},
        http_server=True,
        http_port=0,
    )
    activate(h)
    assert h.server.http_address is not None
    host, port = h.server.http_address
    assert host == "127.0.0.1"
    base = f"http://{host}:{port}/api/v1"
    h.listen("pair")
    h.publish("a", {"v": 1}, 7 * S)  # alone: dropped at its timeout
    h.publish("a", "{not json", 8 * S)
    assert h.spin_until(lambda: h.server.stats()["pair"]["dropped_incomplete"] == 1)
    h.publish("a", {"v": 2}, 9 * S)
    h.publish("b", {"w": 2}, 9 * S)
    h.wait_for_output("pair")

    status, body = get(f"{base}/metrics")
    assert status == 200
    document = json.loads(body)
    assert document["groups"]["pair"] == {
        "published": 1,
        "published_partial": 0,
        "dropped_incomplete": 1,
        "superseded": 0,
        "late": 0,
        "overflowed": 0,
        "renamed_keys": 0,
        "pending": 0,
    }
    assert document["inputs"] == {h.topic("a"): {"malformed": 1}, h.topic("b"): {"malformed": 0}}
    status, text = get(f"{base}/metrics/prometheus")
    assert status == 200
    assert 'dc_group_published_total{group="pair"} 1' in text.splitlines()
    assert 'dc_group_dropped_incomplete_total{group="pair"} 1' in text.splitlines()
    assert f'dc_group_malformed_total{{topic="{h.topic("a")}"}} 1' in text.splitlines()
    assert get(f"{base}/health") == (200, '{"status": "ok"}')

    assert h.server.trigger_deactivate() == TransitionCallbackReturn.SUCCESS
    assert h.server.http_address is None
    with pytest.raises(urllib.error.URLError):
        urllib.request.urlopen(f"{base}/health", timeout=5)


def test_a_taken_metrics_port_is_a_warning_and_a_free_one_serves(start: Any, capfd: pytest.CaptureFixture[str]) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        h = start({"pair": {"inputs": ["a", "b"], "sync_delay": 0.5}}, http_server=True, http_port=port)
        activate(h)
        assert h.server.http_address is not None
        host, bound = h.server.http_address
        assert bound != port
        h.listen("pair")
        h.publish("a", {"v": 1}, 9 * S)
        h.publish("b", {"w": 2}, 9 * S)
        h.wait_for_output("pair")
        document = json.loads(get(f"http://{host}:{bound}/api/v1/metrics")[1])
        assert document["groups"]["pair"]["published"] == 1
    err = capfd.readouterr().err
    assert f"127.0.0.1:{port} is taken (another DC on this machine?); serving on 127.0.0.1:{bound} instead" in err


def test_a_group_feeds_another_group(start: Any) -> None:
    h = start(
        {
            "memory_uptime": {"inputs": ["memory", "uptime"], "sync_delay": 0.5},
            "system": {"inputs": ["memory_uptime", "cpu"], "sync_delay": 0.5, "tags": ["db"]},
        }
    )
    activate(h)
    h.listen("system")
    h.publish("cpu", {"usage": 12.5}, 50 * S)
    h.publish("memory", {"used": 1}, 50 * S, group_key="memory")
    h.publish("uptime", {"time": 2}, 50 * S + S // 10, group_key="uptime")
    (record,) = h.wait_for_output("system")
    assert record.data == {
        "memory_uptime": {"memory": {"used": 1}, "uptime": {"time": 2}, "name": "memory_uptime"},
        "cpu": {"usage": 12.5},
        "tags": ["db"],
        "name": "system",
    }
    assert record.stamp_ns == 50 * S + S // 10
    assert record.group_key == "system"


def test_deactivate_stops_intake_and_settles_pending_sets(start: Any) -> None:
    h = start(
        {
            "g": {
                "inputs": ["a", "b"],
                "sync_delay": 0.1,
                "sync_timeout": 60.0,
                "on_sync_timeout": "emit_partial",
            }
        }
    )
    activate(h)
    h.listen("g")
    h.publish("a", {"v": 1}, 3 * S)
    assert h.spin_until(lambda: h.server.stats()["g"]["pending"] == 1)
    assert h.server.trigger_deactivate() == TransitionCallbackReturn.SUCCESS
    (record,) = h.wait_for_output("g")
    assert record.data["missing_inputs"] == [h.topic("b")]
    assert h.spin_until(lambda: h.server.count_subscribers(h.topic("a")) == 0)
    # Active again: the group works as before.
    assert h.server.trigger_activate() == TransitionCallbackReturn.SUCCESS
    h.wait_matched("a")
    h.publish("a", {"v": 2}, 4 * S)
    h.publish("b", {"w": 2}, 4 * S)
    records = h.wait_for_output("g", 2)
    assert records[1].data == {"a": {"v": 2}, "b": {"w": 2}, "name": "g"}


def test_a_bad_configuration_fails_configure_and_keeps_the_node_alive(start: Any) -> None:
    h = start({"g": {"inputs": ["a"]}})
    params = Path(h.server.params_file)
    params.write_text(yaml.safe_dump({"group_server": {"ros__parameters": {"groups": ["g"], "g": {"input": ["/a"]}}}}))
    assert h.server.trigger_configure() == TransitionCallbackReturn.FAILURE
    assert h.server.lifecycle_state == "unconfigured"
    params.write_text(yaml.safe_dump({"group_server": {"ros__parameters": {"groups": ["g"], "g": {"inputs": ["/a"]}}}}))
    assert h.server.trigger_configure() == TransitionCallbackReturn.SUCCESS


def test_records_destination_server_reads_are_kept_until_acknowledged_and_sent_again_to_it_alone(
    start: Any, tmp_path: Path
) -> None:
    from dc_core.handoff import ACK_TOPIC, RESEND_TOPIC, ack_document, ack_qos, parse_frame_key, resent_topic

    h = start({"g": {"inputs": ["a"], "sync_delay": 0.1}})
    output = h.topic("g")
    params = tmp_path / "params.yaml"  # the fixture's: a destination_server of the same file reads the output
    document = yaml.safe_load(params.read_text())
    document["destination_server"] = {
        "ros__parameters": {
            "destination_plugins": ["file"],
            "file": {"plugin": "dc_destinations/File", "inputs": [output]},
        }
    }
    params.write_text(yaml.safe_dump(document))
    activate(h)
    keys: list[tuple[int, int, int, int]] = []

    def on_output(msg: Any) -> None:
        key = parse_frame_key(msg.header.frame_id)
        assert key is not None, msg.header.frame_id
        keys.append(key)

    h.helper.create_subscription(StringStamped, output, on_output, QOS)
    resent: list[tuple[int, int, int, int]] = []

    def on_resent(msg: Any) -> None:
        assert resent_topic(msg.header.frame_id) == output, msg.header.frame_id
        key = parse_frame_key(msg.header.frame_id)
        assert key is not None
        resent.append(key)

    h.helper.create_subscription(StringStamped, RESEND_TOPIC, on_resent, QOS)
    acks = h.helper.create_publisher(StringStamped, ACK_TOPIC, ack_qos())
    for n in range(3):
        h.publish("a", {"n": n}, (n + 1) * S)
    assert h.spin_until(lambda: len(keys) == 3), keys
    writer = keys[0][0]
    assert [k[1] for k in keys] == [1, 2, 3]
    assert h.server.handoff is not None
    assert h.server.handoff.metrics()[output]["unacked"] == 3

    def ack(instance: str, floor: int) -> None:
        msg = StringStamped()
        msg.data = ack_document(instance, [(output, writer, floor)])
        acks.publish(msg)

    assert h.spin_until(lambda: acks.get_subscription_count() > 0)
    # A destination_server heard of for the first time, which has committed record 1: 2 and 3 again.
    ack("first", 1)
    assert h.spin_until(lambda: len(resent) == 2), resent
    assert [k[1] for k in resent] == [2, 3], "sent again under their own numbers"
    assert len(keys) == 3, "not on the output topic, where group inputs or conditions would take them for new"
    ack("first", 3)
    assert h.spin_until(lambda: h.server.handoff is not None and h.server.handoff.metrics()[output]["unacked"] == 0)
    assert h.server.handoff.metrics()[output] == {"unacked": 0, "unacked_bytes": 0, "dropped": 0, "resent": 2}


def test_large_merged_records_get_a_history_bounded_in_bytes(start: Any) -> None:
    h = start({"frames": {"inputs": ["camera"], "sync_delay": 0.1, "history_bytes": 500_000}})
    activate(h)
    live = h.listen("frames")
    blob = "x" * 100_000
    for i in range(12):
        h.publish("camera", {"i": i, "image": blob}, (10 + i) * S)
    h.wait_for_output("frames", 12)
    history = h.server.metrics_document()["history"][h.topic("frames")]
    assert history["largest_record"] > 100_000
    assert history["depth"] == 500_000 // history["largest_record"] == 4
    # A transient-local subscriber joining now gets what DDS holds: the newest 4, not 12.
    late: list[int] = []
    h.helper.create_subscription(
        StringStamped, h.topic("frames"), lambda msg: late.append(json.loads(msg.data)["camera"]["i"]), record_qos(1000)
    )
    assert h.spin_until(lambda: len(late) >= 4)
    h.spin_until(lambda: len(late) > 4, timeout=0.5)  # nothing beyond the history
    assert late == [8, 9, 10, 11]
    assert [r.data["camera"]["i"] for r in live] == list(range(12))  # the replacement lost nothing live
