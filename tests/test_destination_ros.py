"""destination_server as a real lifecycle node: records from an independent publisher reach a file.

The server runs in this process under its own executor; the publisher lives in a second rclpy
context (its own DDS participant), as another process' node would.
"""

from __future__ import annotations

import json
import sqlite3
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.lifecycle import TransitionCallbackReturn
from rclpy.qos import QoSProfile, ReliabilityPolicy

from dc_core.lifecycle import ServerLoop
from dc_destinations.buffer import FILE_NAME
from dc_destinations.server import DestinationServer
from dc_interfaces.msg import StringStamped
from tests.hostile_records import hostile_stream

DEADLINE_S = 15.0
STAMP = (1_700_000_000, 5_000_000)  # 2023-11-14T22:13:20.005Z


@dataclass
class Running:
    server: DestinationServer
    executor: SingleThreadedExecutor
    publisher: Any
    topic: str
    out_file: Path

    def __post_init__(self) -> None:
        # run_server's loop: the server's intake takes the records, the executor the rest.
        self.loop = ServerLoop(self.executor, self.server.intake)

    def spin_until(self, done: Callable[[], bool]) -> bool:
        deadline = time.monotonic() + DEADLINE_S
        while time.monotonic() < deadline:
            if done():
                return True
            self.loop.spin_once(timeout_sec=0.02)
        return done()

    def wait_for_subscription(self) -> None:
        assert self.spin_until(lambda: self.publisher.get_subscription_count() >= 1), "server never subscribed"

    def publish(self, data: str, stamp: tuple[int, int] = STAMP) -> None:
        msg = StringStamped()
        msg.header.stamp.sec, msg.header.stamp.nanosec = stamp
        msg.data = data
        self.publisher.publish(msg)

    def lines(self) -> list[dict[str, Any]]:
        if not self.out_file.exists():
            return []
        written = self.out_file.read_bytes()
        complete = written[: written.rfind(b"\n") + 1]  # a line being written is read next time
        return [json.loads(line) for line in complete.decode().splitlines()]


def write_params(tmp_path: Path, topic: str, extra: str = "") -> Path:
    params = tmp_path / "params.yaml"
    params.write_text(
        f"""
destination_server:
  ros__parameters:
    flb:
      flush: 0.05
      grace: 2.0
      storage_path: "{tmp_path / "buffer"}"
    destination_plugins: ["disk", "flb_pgsql"]
    disk:
      plugin: "dc_destinations/FlbFile"
      inputs: ["{topic}"]
      path: "{tmp_path / "out"}"
      file: "records.jsonl"
      time_format: "iso8601"
    flb_pgsql:
      plugin: "dc_destinations/Null"
      inputs: ["{topic}"]
{extra}
"""
    )
    return params


@pytest.fixture
def running(tmp_path: Path) -> Iterator[Running]:
    topic = f"/dc_test/records_{uuid.uuid4().hex[:8]}"
    rclpy.init()  # the server's node uses the default context, a fresh one per init
    publisher_context = Context()
    rclpy.init(context=publisher_context)
    try:
        server = DestinationServer(str(write_params(tmp_path, topic)))
        executor = SingleThreadedExecutor()
        executor.add_node(server)
        publisher_node = rclpy.create_node(f"dc_test_publisher_{uuid.uuid4().hex[:8]}", context=publisher_context)
        publisher = publisher_node.create_publisher(
            StringStamped, topic, QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        )
        try:
            yield Running(server, executor, publisher, topic, tmp_path / "out" / "records.jsonl")
        finally:
            if server.lifecycle_state in ("active", "inactive"):
                server.trigger_shutdown()
            executor.shutdown()
            server.destroy_node()
            publisher_node.destroy_node()
    finally:
        rclpy.shutdown(context=publisher_context)
        rclpy.shutdown()


def test_published_records_reach_the_file_destination(running: Running) -> None:
    server = running.server
    assert server.trigger_configure() == TransitionCallbackReturn.SUCCESS
    assert server.trigger_activate() == TransitionCallbackReturn.SUCCESS
    running.wait_for_subscription()

    for i in range(5):
        running.publish(json.dumps({"name": "uptime", "time": i, "tags": ["disk"]}))
    running.publish(json.dumps({"time": 99, "tags": ["dis"]}))  # a substring of "disk": goes nowhere
    running.publish(json.dumps({"time": 98, "tags": ["flb_pg"]}))  # a substring of "flb_pgsql": goes nowhere
    running.publish("this is not JSON")
    running.publish("[1, 2]")

    assert running.spin_until(lambda: len(running.lines()) >= 5), f"file has {running.lines()}"
    assert running.spin_until(lambda: server.stats.received >= 9)
    lines = running.lines()
    assert len({line.pop("record_id") for line in lines}) == 5, "each record carries its own record_id"
    assert lines == [{"date": "2023-11-14T22:13:20.005000Z", "name": "uptime", "time": i} for i in range(5)]
    assert server.stats.malformed == 2
    assert sum(server.stats.unrouted.values()) == 2
    assert server.intake_metrics()["routed"] == 5

    assert server.trigger_deactivate() == TransitionCallbackReturn.SUCCESS
    assert running.lines()[-1]["time"] == 4  # nothing duplicated or lost by the stop
    assert len(running.lines()) == 5


def test_a_volatile_topic_keeps_each_publishers_position_and_a_restart_counts_what_it_missed(
    running: Running,
) -> None:
    """Records of your own nodes are never replayed, so their keys only tell where each publisher was:
    the buffer keeps the last of each run, and a server started on it counts the records published
    while none was listening."""
    server = running.server
    assert server.trigger_configure() == TransitionCallbackReturn.SUCCESS
    assert server.trigger_activate() == TransitionCallbackReturn.SUCCESS
    running.wait_for_subscription()
    for i in range(30):  # published before the loop takes any: they arrive together
        running.publish(json.dumps({"n": i, "tags": ["disk"]}))
    assert running.spin_until(lambda: len(running.lines()) == 30)
    assert server.trigger_deactivate() == TransitionCallbackReturn.SUCCESS
    kept = [seq for topic, _, seq in _hop_keys(running) if topic == running.topic]
    assert kept and max(kept) == 30 and len(kept) < 30, kept
    assert server.trigger_cleanup() == TransitionCallbackReturn.SUCCESS

    for i in range(30, 40):  # nobody listens: lost, as for any volatile subscriber
        running.publish(json.dumps({"n": i, "tags": ["disk"]}))
    assert server.trigger_configure() == TransitionCallbackReturn.SUCCESS  # the buffer read again
    assert server.trigger_activate() == TransitionCallbackReturn.SUCCESS
    running.wait_for_subscription()
    for i in range(40, 45):
        running.publish(json.dumps({"n": i, "tags": ["disk"]}))
    assert running.spin_until(lambda: len(running.lines()) == 35)
    assert [line["n"] for line in running.lines()] == [*range(30), *range(40, 45)]
    hop = server.hop_metrics()[running.topic]
    assert (hop["missing"], hop["gaps"], hop["duplicates"]) == (10, 1, 0), hop


def _hop_keys(running: Running) -> list[tuple[str, int, int]]:
    """The hop keys in the server's buffer, read as `dc buffer` would (another connection)."""
    folder = Path(running.out_file).parent.parent / "buffer"
    with sqlite3.connect(folder / FILE_NAME) as conn:
        return [
            (str(t), int(ns), int(seq)) for t, ns, seq in conn.execute("SELECT topic, source_ns, seq FROM hop_seen")
        ]


def test_a_lone_surrogate_record_does_not_stall_the_records_after_it(running: Running) -> None:
    # The reported poison record: its group commit failed for good and every record after it waited
    # in memory, uncounted.
    server = running.server
    assert server.trigger_configure() == TransitionCallbackReturn.SUCCESS
    assert server.trigger_activate() == TransitionCallbackReturn.SUCCESS
    running.wait_for_subscription()
    running.publish('{"t": "\\udcff", "tags": ["disk"]}')
    for n in range(5):
        running.publish(json.dumps({"n": n, "tags": ["disk"]}))
    assert running.spin_until(lambda: len(running.lines()) == 5), f"file has {running.lines()}"
    assert [line["n"] for line in running.lines()] == list(range(5))
    assert server.stats.malformed == 1
    assert server.pipeline is not None and server.pipeline.healthy()


def test_hostile_records_are_counted_and_every_valid_one_is_delivered_once(running: Running) -> None:
    stream = hostile_stream(valid=1000, hostile=2000, tags=["disk"], seed=20261124)
    server = running.server
    assert server.trigger_configure() == TransitionCallbackReturn.SUCCESS
    assert server.trigger_activate() == TransitionCallbackReturn.SUCCESS
    running.wait_for_subscription()
    for start in range(0, len(stream), 200):
        for item in stream[start : start + 200]:
            running.publish(item.text)
        # Chunks the server has taken before the next: a queue overflow is not what this test is about.
        sent = min(start + 200, len(stream))

        def chunk_taken(sent: int = sent) -> bool:
            return server.stats.received >= sent

        assert running.spin_until(chunk_taken), server.stats.as_dict()

    valid = [item for item in stream if not item.malformed]
    assert running.spin_until(lambda: len(running.lines()) >= len(valid)), f"{len(running.lines())} lines"
    lines = running.lines()
    assert sorted(line["n"] for line in lines if "n" in line) == list(range(1000)), "each numbered record once"
    odd = sorted(item.odd for item in valid if item.odd is not None)
    assert sorted(line["odd"] for line in lines if "odd" in line) == odd, "each odd valid record once"
    assert all(line["record_id"] != "forged" and line["date"] != "forged" for line in lines)
    malformed = sum(item.malformed for item in stream)
    assert server.stats.malformed == malformed
    assert server.stats.received == len(stream) and server.stats.routed == len(valid)
    assert not server.stats.unrouted
    assert server.hop_metrics()[running.topic]["missing"] == 0
    assert server.pipeline is not None and server.pipeline.healthy()
    assert server.pipeline.metrics()["disk"]["malformed"] == 0, "all caught at intake"


def test_a_tag_routed_nowhere_is_a_warning_once_then_counted(
    running: Running, capfd: pytest.CaptureFixture[str]
) -> None:
    server = running.server
    assert server.trigger_configure() == TransitionCallbackReturn.SUCCESS
    assert server.trigger_activate() == TransitionCallbackReturn.SUCCESS
    running.wait_for_subscription()
    for n in range(3):
        running.publish(json.dumps({"n": n, "tags": ["dsik"]}))
    assert running.spin_until(lambda: sum(server.stats.unrouted.values()) == 3)
    warnings = [line for line in capfd.readouterr().err.splitlines() if "reaches no destination" in line]
    assert len(warnings) == 1 and warnings[0].startswith("[WARN]"), warnings
    assert "tags ['dsik']" in warnings[0] and "destinations listening here: disk, flb_pgsql" in warnings[0]


def test_a_compatibility_key_without_effect_is_logged_once_at_configure(
    running: Running, capfd: pytest.CaptureFixture[str]
) -> None:
    params = Path(running.server.params_file)
    params.write_text(params.read_text().replace("grace: 2.0", 'grace: 2.0\n      storage_checksum: "on"'))
    assert running.server.trigger_configure() == TransitionCallbackReturn.SUCCESS
    said = [line for line in capfd.readouterr().err.splitlines() if "storage_checksum" in line]
    assert len(said) == 1 and said[0].startswith("[WARN]"), said
    assert (
        "destination_server.flb.storage_checksum: accepted for the original's files, has no effect because "
        "SQLite checks its own pages"
    ) in said[0]


def test_reactivation_resumes_delivery(running: Running) -> None:
    server = running.server
    assert server.trigger_configure() == TransitionCallbackReturn.SUCCESS
    assert server.trigger_activate() == TransitionCallbackReturn.SUCCESS
    running.wait_for_subscription()
    running.publish(json.dumps({"run": 1, "tags": ["disk"]}))
    assert running.spin_until(lambda: len(running.lines()) == 1)

    assert server.trigger_deactivate() == TransitionCallbackReturn.SUCCESS
    assert running.spin_until(lambda: running.publisher.get_subscription_count() == 0), "intake not stopped"

    assert server.trigger_activate() == TransitionCallbackReturn.SUCCESS
    running.wait_for_subscription()
    running.publish(json.dumps({"run": 2, "tags": ["disk"]}))
    assert running.spin_until(lambda: len(running.lines()) == 2)
    assert [line["run"] for line in running.lines()] == [1, 2]

    assert server.trigger_deactivate() == TransitionCallbackReturn.SUCCESS
    assert server.trigger_cleanup() == TransitionCallbackReturn.SUCCESS
    assert server.plugins == {}


def test_unstamped_message_gets_the_reception_time(running: Running) -> None:
    server = running.server
    assert server.trigger_configure() == TransitionCallbackReturn.SUCCESS
    assert server.trigger_activate() == TransitionCallbackReturn.SUCCESS
    running.wait_for_subscription()
    before = time.time()
    running.publish(json.dumps({"tags": ["disk"]}), stamp=(0, 0))
    assert running.spin_until(lambda: len(running.lines()) == 1)
    date = running.lines()[0]["date"]
    assert date[:4] != "1970"
    assert date >= time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(int(before)))


def test_invalid_configuration_fails_configure_and_can_be_retried(running: Running, tmp_path: Path) -> None:
    server = running.server
    write_params(tmp_path, running.topic, extra="    disk_typo: 1\n")
    assert server.trigger_configure() == TransitionCallbackReturn.FAILURE
    assert server.lifecycle_state == "unconfigured"
    write_params(tmp_path, running.topic)
    assert server.trigger_configure() == TransitionCallbackReturn.SUCCESS
    assert server.config is not None
    assert server.config.names == ["disk", "flb_pgsql"]


def test_a_middleware_without_sequence_numbers_is_said_once_at_startup(
    running: Running, capfd: pytest.CaptureFixture[str]
) -> None:
    """The PyPI wheels have Fast DDS only: the detection is forced to answer as Cyclone DDS's
    rmw_feature_supported does (False); what the server then says is what a Cyclone user reads."""
    server = running.server
    server.sequence_numbers = lambda identifier: False
    for _ in range(2):  # a second activation (pause and resume) does not say it again
        assert server.trigger_configure() == TransitionCallbackReturn.SUCCESS
        assert server.trigger_activate() == TransitionCallbackReturn.SUCCESS
        assert server.trigger_deactivate() == TransitionCallbackReturn.SUCCESS
        assert server.trigger_cleanup() == TransitionCallbackReturn.SUCCESS
    lines = [line for line in capfd.readouterr().err.splitlines() if "publication sequence numbers" in line]
    assert len(lines) == 1, lines
    (line,) = lines
    assert line.startswith("[WARN]"), line  # records of a publisher that is not DC's are affected
    assert f"your own nodes' records on {running.topic}" in line
    assert "duplicates, never a loss" in line and "not counted" in line


def test_a_middleware_with_sequence_numbers_is_not_mentioned(
    running: Running, capfd: pytest.CaptureFixture[str]
) -> None:
    # The real detection: Fast DDS answers rmw_feature_supported(publication sequence number) = true.
    server = running.server
    assert server.trigger_configure() == TransitionCallbackReturn.SUCCESS
    assert server.trigger_activate() == TransitionCallbackReturn.SUCCESS
    assert "publication sequence numbers" not in capfd.readouterr().err
