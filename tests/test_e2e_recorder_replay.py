"""The Recorder on a recorded robot: `dc replay` plays a real bag, a Moving-based trigger fires, dc-bringup writes
the incident's MCAP file, whose /odom messages are the bag's of the window.

The bag (cp24_obstacle-avoider, tests/data/bags/SOURCE.md) has the robot moving from its first /odom on:
``if_all_conditions: ["moving"]`` fires once, when Moving has seen enough fast messages. The window starts
pre_trigger before that, before the bag's first message, so the file must hold the bag's /odom from its
very first message on, none missing; its end is checked against a bare subscriber's log of the same run.
"""

from __future__ import annotations

import subprocess
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from rclpy.qos import QoSProfile

from tests.bringup_util import BIN, Bringup
from tests.robot_helpers import odom_log
from tests.test_e2e_recorder import read_odom_stamps, stamp_of

pytestmark = pytest.mark.e2e

BAG = Path(__file__).parent / "data" / "bags" / "cp24_obstacle-avoider"
RATE = 2.0  # /odom at 10 Hz: a window of a few seconds of bag
POST_TRIGGER = 1.5
# The bare subscriber and the recorder take a message at slightly different instants, more so on a
# loaded machine: the window's end is checked by the bare subscriber's clock within this.
EDGE_NS = 500_000_000

PARAMS = f"""
measurement_server:
  ros__parameters:
    measurement_plugins: ["incidents", "operator"]
    condition_plugins: ["moving"]
    save_local_base_path: "data/"
    moving:
      plugin: "dc_conditions/Moving"
      odom_topic: "/odom"
      speed_threshold: 0.1
    incidents:
      plugin: "dc_measurements/Recorder"
      topics: ["/odom", "/tf", "/tf_static"]
      if_all_conditions: ["moving"]
      polling_interval: 100
      pre_trigger: 2.0
      post_trigger: {POST_TRIGGER}
      tags: ["out"]
    operator:
      plugin: "dc_measurements/Recorder"
      topics: ["/odom"]
      pre_trigger: 1.0
      post_trigger: 0.5
      save_path: "operator/%H%M%S"
      tags: ["out"]
destination_server:
  ros__parameters:
    destination_plugins: ["out"]
    out:
      plugin: "dc_destinations/Stdout"
      inputs: ["/dc/measurement/incidents", "/dc/measurement/operator"]
"""


def bag_odom_stamps() -> list[int]:
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    with AnyReader([BAG], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        connections = [c for c in reader.connections if c.topic == "/odom"]
        return [stamp_of(reader.deserialize(d, c.msgtype)) for c, _, d in reader.messages(connections=connections)]


@dataclass
class Run:
    record: dict[str, Any]
    operator: dict[str, Any]
    odom: list[tuple[int, int]]  # (receive time ns, header stamp ns), as the bare subscriber got them
    home: Path


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Run]:
    tmp = tmp_path_factory.mktemp("recorder-replay")
    params = tmp / "incidents.yaml"
    params.write_text(PARAMS)
    with Bringup(params, tmp / "home") as dc, odom_log(dc.domain_id, QoSProfile(depth=1000)) as odom:
        dc.wait_ready()
        replay: subprocess.Popen[str] | None = None
        try:
            # Played once Moving, the recorders and the bare subscriber all take /odom: each gets every message.
            replay = subprocess.Popen(
                [str(BIN / "dc"), "replay", str(BAG), "--rate", str(RATE), "--no-clock", "--delay", "0",
                 "--topics", "/odom", "/tf", "/tf_static", "--wait-for", "/odom=4"],
                env=dc.env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
            )  # fmt: skip
            dc.wait_until(lambda: bool(dc.named("incidents")), 60, "the incident's record")
            (record,) = dc.named("incidents")
            # A recorder without conditions has no timer while idle: a trigger starts its own polls.
            trigger = [str(BIN / "dc"), "trigger", "operator", "--reason", "after the robot started"]
            assert subprocess.run(trigger, env=dc.env, capture_output=True, timeout=60).returncode == 0
            dc.wait_until(lambda: bool(dc.named("operator")), 60, "the operator's incident")
            (operator,) = dc.named("operator")
        finally:
            if replay is not None and replay.poll() is None:
                replay.terminate()
                try:
                    replay.wait(10)
                except subprocess.TimeoutExpired:
                    replay.kill()
                    replay.wait()
    yield Run(record, operator, odom, dc.home)


def test_a_replayed_bag_gives_an_incident_file_with_the_odom_of_its_window(run: Run) -> None:
    record = run.record
    assert [t["reason"] for t in record["triggers"]] == ["conditions"]
    recorded = read_odom_stamps(run.home / record["local_paths"]["mcap"])
    # From the bag's first /odom on (the window began before it), none missing, in the bag's order.
    bag = bag_odom_stamps()
    assert recorded and recorded == bag[: len(recorded)]
    # Its end: the last message the bare subscriber took before the window's end, by its clock.
    end_ns = int(record["end"] * 1e9)
    received = {stamp: at for at, stamp in run.odom}
    assert abs(received[recorded[-1]] - end_ns) <= EDGE_NS
    after = [at for at, stamp in run.odom if stamp not in set(recorded)]
    assert not after or after[0] >= end_ns - EDGE_NS
    topics = {t["topic"]: t for t in record["topics"]}
    assert topics["/odom"]["messages"] == len(recorded) and topics["/tf_static"]["messages"] >= 1
    assert topics["/tf"]["messages"] > 0 and not record["cut_by_memory_bound"]


def test_a_recorder_without_conditions_is_triggered_by_dc_trigger_and_writes_its_window(run: Run) -> None:
    record = run.operator
    assert [t["reason"] for t in record["triggers"]] == ["after the robot started"]
    recorded = read_odom_stamps(run.home / record["local_paths"]["mcap"])
    assert recorded and recorded == [s for s in bag_odom_stamps() if recorded[0] <= s <= recorded[-1]]
