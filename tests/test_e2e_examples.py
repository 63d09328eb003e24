"""The seed's configuration examples through `dc-bringup`, read as a user reads them: on stdout.

Each test starts the real launcher, which starts each server as its own process and drives them
through their lifecycle; records arrive on stdout from the Stdout destination.
"""

from __future__ import annotations

import itertools
import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.bringup_util import REPO, Bringup, dc

EXAMPLES = REPO / "params" / "examples"
pytestmark = pytest.mark.e2e


def uptime_now() -> float:
    return float(Path("/proc/uptime").read_text().split()[0])


@pytest.mark.usefixtures("bringup_mode")
def test_example_1_uptime_every_second(tmp_path: Path) -> None:
    with Bringup(EXAMPLES / "example_1.yaml", tmp_path) as run:
        records = run.wait_records(4, timeout=60)
    first = records[0]
    assert {"date", "time", "run_id", "name"} <= set(first)
    assert "tags" not in first, "routing tags are removed before delivery"
    assert first["name"] == "uptime" and first["run_id"] == "1"
    assert abs(first["time"] - uptime_now()) < 60
    dates = [r["date"] for r in records[:4]]
    gaps = [b - a for a, b in itertools.pairwise(dates)]
    assert all(0.8 < g < 1.2 for g in gaps), gaps
    assert run.returncode == 0


@pytest.mark.usefixtures("bringup_mode")
def test_stdout_carries_the_records_alone_when_fast_dds_prints_errors(tmp_path: Path) -> None:
    """Fast DDS prints its own errors from C++ on descriptor 1 (here: a profile file it cannot parse,
    read by dc-bringup and every server); `dc-bringup params.yaml | jq` reads records only, and the
    errors are on stderr."""
    profile = tmp_path / "broken_profile.xml"
    profile.write_text("<dds><profiles><unclosed>")
    with Bringup(EXAMPLES / "example_1.yaml", tmp_path, env={"FASTRTPS_DEFAULT_PROFILES_FILE": str(profile)}) as run:
        run.wait_records(2, timeout=60)
    lines = [line for line in run.stdout if line.strip()]
    assert lines and all(json.loads(line)["name"] == "uptime" for line in lines), lines
    assert any("XMLPARSER" in line for line in run.stderr)


def test_example_2_flush_every_three_seconds_delivers_in_batches(tmp_path: Path) -> None:
    with Bringup(EXAMPLES / "example_2.yaml", tmp_path) as run:
        records = run.wait_records(6, timeout=60)
        arrivals = run.record_times()
    dates = [r["date"] for r in records[:6]]
    assert all(0.8 < b - a < 1.2 for a, b in itertools.pairwise(dates)), dates
    # Collected every second, delivered every 3 s: several records arrive within a few ms.
    bursts = sum(1 for a, b in itertools.pairwise(arrivals) if b - a < 0.1)
    assert bursts >= 2, arrivals


@pytest.mark.usefixtures("bringup_mode")
def test_example_3_only_three_records(tmp_path: Path) -> None:
    with Bringup(EXAMPLES / "example_3.yaml", tmp_path) as run:
        run.wait_records(3, timeout=60)
        run.wait_stderr("uptime: done", timeout=10)
        # The timer is stopped: nothing else can come. Give a late record its chance to show.
        deadline = time.monotonic() + 3
        while time.monotonic() < deadline and len(run.records()) == 3:
            time.sleep(0.2)
    assert len(run.records()) == 3


def test_the_uptime_demo_prints_uptime_every_5_s_with_the_robot_name_and_machine_id(tmp_path: Path) -> None:
    with Bringup(REPO / "params" / "demos" / "uptime_stdout.yaml", tmp_path) as run:
        records = run.wait_records(2, timeout=60)
    first, second = records[:2]
    assert first["robot_name"] == "C3PO" and first["id"] == Path("/etc/machine-id").read_text().strip()
    assert first["name"] == "uptime" and first["run_id"] == "1"
    assert 4.5 < second["date"] - first["date"] < 5.5 and abs(first["time"] - uptime_now()) < 60
    # debug: true logs each published record too.
    assert any("measurement uptime published:" in line for line in run.stderr)


def test_the_custom_uptime_demo_publishes_records_that_fail_its_schema_and_calls_the_hook(tmp_path: Path) -> None:
    # The plugin comes from the separate package examples/dc_uptime_custom (make install-demos and make install-test install it).
    with Bringup(REPO / "params" / "demos" / "uptime_custom_stdout.yaml", tmp_path) as run:
        records = run.wait_records(2, timeout=60)
        run.wait_until(
            lambda: sum("on_failed_validation called" in line for line in run.stderr) >= 2, 15, "the hook's second call"
        )
    assert [r["name"] for r in records[:2]] == ["uptime_custom", "uptime_custom"]
    assert records[0]["robot_name"] == "C3PO" and abs(records[0]["time"] - uptime_now()) < 60
    # Each record: DC's validation error, then the plugin's hook, which counts.
    logged = [line for line in run.stderr if "validation failed" in line or "on_failed_validation" in line]
    assert "uptime_custom: validation failed (published anyway)" in logged[0]
    assert "is greater than the maximum of 0" in logged[0]
    assert f"on_failed_validation called for time={records[0]['time']} (1 so far)" in logged[1]
    assert "(2 so far)" in logged[3]


@pytest.mark.parametrize("example", ["example_6_fixed.yaml", "example_7_fixed.yaml"])
@pytest.mark.usefixtures("bringup_mode")
def test_examples_6_and_7_deliver_what_dc_pub_publishes(tmp_path: Path, example: str) -> None:
    with Bringup(EXAMPLES / example, tmp_path) as run:
        run.wait_ready()
        published = dc("pub", "/hello-world", '{"hello": "world"}', "--count", "3", "--rate", "2", env=run.env)
        assert published.returncode == 0, published.stderr
        records = run.wait_records(1 if "6" in example else 3, timeout=30)
    assert records[0]["hello"] == "world" and records[0]["name"] == "my_string_stamped"
    if "7" in example:
        assert len(records) == 3, "every published record is forwarded once, no duplicate"


def test_example_6_as_printed_warns_and_delivers_nothing(tmp_path: Path) -> None:
    with Bringup(EXAMPLES / "example_6.yaml", tmp_path) as run:
        run.wait_ready()
        assert any("is published by nothing" in line for line in run.stderr)
        dc("pub", "/hello-world", '{"hello": "world"}', "--count", "2", "--rate", "5", env=run.env)
    assert run.records() == []


INDEPENDENT_PUBLISHER = """
import json, sys, time
import rclpy
from rclpy.duration import Duration
from rclpy.qos import QoSProfile, ReliabilityPolicy
from dc_interfaces.msg import StringStamped
rclpy.init()
node = rclpy.create_node("robot_app")
qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
pub = node.create_publisher(StringStamped, "/robot/events", qos)
deadline = time.monotonic() + 30
while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
    rclpy.spin_once(node, timeout_sec=0.05)
for i in range(20):
    msg = StringStamped()
    msg.header.stamp.sec = 1700000000 + i
    msg.data = json.dumps({"seq": i, "event": "dock"})
    msg.group_key = "events"
    pub.publish(msg)
sys.exit(0 if pub.wait_for_all_acked(Duration(seconds=30)) else 4)
"""


def test_independent_rclpy_node_reaches_a_file_destination(tmp_path: Path) -> None:
    out = tmp_path / "out"
    params = tmp_path / "params.yaml"
    params.write_text(f"""
measurement_server:
  ros__parameters:
    measurement_plugins: ["events"]
    events:
      plugin: "dc_measurements/StringStamped"
      topic: "/robot/events"
      timer_based: false
      tags: ["file"]
destination_server:
  ros__parameters:
    destination_plugins: ["file"]
    file:
      plugin: "dc_destinations/File"
      path: "{out}"
      file: "events.jsonl"
      time_format: "iso8601"
      inputs: ["/dc/measurement/events"]
""")
    with Bringup(params, tmp_path / "home") as run:
        run.wait_ready()
        subprocess.run([sys.executable, "-c", INDEPENDENT_PUBLISHER], env=run.env, check=True, timeout=60)
        target = out / "events.jsonl"
        run.wait_until(lambda: target.exists() and len(target.read_text().splitlines()) >= 20, 30, "20 lines")
    lines = [json.loads(line) for line in (out / "events.jsonl").read_text().splitlines()]
    assert [r["seq"] for r in lines] == list(range(20))
    # The source's stamp is kept: record i was stamped 1700000000 + i.
    assert lines[3]["date"] == "2023-11-14T22:13:23.000000Z"
