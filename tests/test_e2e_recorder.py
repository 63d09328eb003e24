"""The Recorder end to end: `dc sim` drives, a Moving-based trigger fires at each stop, dc-bringup writes MCAP files.

A bare subscriber in this process logs every /odom message it receives with its receive time: each
incident's file must hold exactly the /odom messages of its window (give or take one at each edge, the
two subscriptions receive a message at slightly different instants), read back with rosbags and mcap.
"""

from __future__ import annotations

import json
import subprocess
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from nav_msgs.msg import Odometry
from rclpy.qos import QoSProfile, ReliabilityPolicy

from tests.bringup_util import BIN, Bringup
from tests.robot_helpers import odom_log

pytestmark = pytest.mark.e2e

RATE = 4.0
# Incidents of the robot's stops to wait for (the first may be its standing at the start).
STOPS = 3

PARAMS = """
measurement_server:
  ros__parameters:
    measurement_plugins: ["incidents"]
    condition_plugins: ["moving"]
    save_local_base_path: "data/"
    moving:
      plugin: "dc_conditions/Moving"
      odom_topic: "/odom"
      speed_threshold: 0.2
    incidents:
      plugin: "dc_measurements/Recorder"
      topics: ["/odom", "/tf", "/tf_static", "/never_published"]
      if_none_conditions: ["moving"]
      polling_interval: 100
      pre_trigger: 1.0
      post_trigger: 1.5
      tags: ["out"]
destination_server:
  ros__parameters:
    destination_plugins: ["out"]
    out:
      plugin: "dc_destinations/Stdout"
      inputs: ["/dc/measurement/incidents"]
"""


OPERATOR = {"service", "operator saw a bump"}


def reasons(record: dict[str, Any]) -> set[str]:
    return {t["reason"] for t in record["triggers"]}


def stamp_of(message: Odometry) -> int:
    return int(message.header.stamp.sec) * 1_000_000_000 + int(message.header.stamp.nanosec)


def _logged_stops(records: list[dict[str, Any]], odom: list[tuple[int, int]]) -> list[dict[str, Any]]:
    """The incidents of the robot's stops whose window began a second after the bare subscriber's first /odom."""
    if not odom:
        return []
    first = odom[0][0]
    return [r for r in records if r["start"] * 1e9 > first + 1e9 and not OPERATOR & reasons(r)]


@dataclass
class Run:
    records: list[dict[str, Any]]
    odom: list[tuple[int, int]]  # (receive time ns, header stamp ns), as the bare subscriber got them
    home: Path


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Run]:
    tmp = tmp_path_factory.mktemp("recorder")
    params = tmp / "incidents.yaml"
    params.write_text(PARAMS)
    with (
        Bringup(params, tmp / "home", args=["--use-sim-time"]) as dc,
        odom_log(dc.domain_id, QoSProfile(depth=200, reliability=ReliabilityPolicy.BEST_EFFORT)) as odom,
    ):
        dc.wait_ready()
        sim: subprocess.Popen[str] | None = None
        try:
            # The server polls on the simulated clock: the simulator runs until the operator's window closed.
            sim = subprocess.Popen(
                [str(BIN / "dc"), "sim", "--clock", "--rate", str(RATE), "--camera-fps", "0"],
                env=dc.env,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.PIPE,
                text=True,
            )
            # Stops whose window the bare subscriber saw whole: under load its first /odom may come
            # seconds after the recorder's (its discovery is its own), and earlier stops do not count.
            dc.wait_until(
                lambda: len(_logged_stops(dc.named("incidents"), odom)) >= STOPS - 1, 90, f"{STOPS - 1} logged stops"
            )
            # An operator's two triggers at once (whichever comes second is inside the window of the first):
            # one file, both reasons. Each answers: opened, or extended (a robot's stop may have opened it).
            calls = [
                subprocess.Popen([str(BIN / "dc"), "trigger", "incidents", *more], env=dc.env, stdout=subprocess.PIPE)
                for more in ([], ["--reason", "operator saw a bump"])
            ]
            for call in calls:
                assert call.wait(30) == 0
            dc.wait_until(
                lambda: any(reasons(r) >= OPERATOR for r in dc.named("incidents")),
                15,
                "the operator's incident",
            )
            records = dc.named("incidents")
            sim.terminate()
            assert sim.wait(10) in (0, -15), sim.stderr.read() if sim.stderr else ""
        finally:
            if sim is not None and sim.poll() is None:
                sim.kill()
                sim.wait()
    yield Run(records, odom, dc.home)


EDGE_NS = 1_500_000_000


def read_odom_stamps(path: Path) -> list[int]:
    from rosbags.highlevel import AnyReader

    with AnyReader([path]) as reader:
        connections = [c for c in reader.connections if c.topic == "/odom"]
        return [
            stamp_of(reader.deserialize(data, connection.msgtype))
            for connection, _, data in reader.messages(connections=connections)
        ]


def test_each_stop_gives_one_file_with_the_odom_of_its_window(run: Run) -> None:
    # The robot stands at the start: that trigger may come before the recorder saw /odom. Every other
    # incident's window lies in the bare subscriber's log.
    incidents = _logged_stops(run.records, run.odom)
    assert len(incidents) >= STOPS - 1, [r["triggers"] for r in run.records]
    log_stamps = [stamp for _, stamp in run.odom]
    for record in incidents:
        # One stop's each, or two stops closer than post_trigger in one window.
        assert {t["reason"] for t in record["triggers"]} == {"conditions"}
        path = run.home / record["local_paths"]["mcap"]
        recorded = read_odom_stamps(path)
        assert recorded, json.dumps(run.records)
        # No message of the window missing between its first and last.
        first = log_stamps.index(recorded[0])
        assert log_stamps[first : first + len(recorded)] == recorded
        # The edges, by the bare subscriber's clock: ±1 message on a quiet machine; in a loaded full run
        # the recording began 35 messages (about 1 s) after its window's start — the two processes take a
        # message at different times, and the recorder then subscribed to a topic only once its graph check
        # (each second) saw a publisher (now it subscribes before: tests/test_e2e_recorder_replay.py and
        # the recorder's own tests check a window's first message). Within 1.5 s is what is asserted here.
        edges = run.odom[first][0], run.odom[first + len(recorded) - 1][0]
        assert abs(edges[0] - record["start"] * 1e9) <= EDGE_NS and abs(edges[1] - record["end"] * 1e9) <= EDGE_NS
        topics = {t["topic"]: t for t in record["topics"]}
        assert topics["/odom"]["messages"] == len(recorded) and topics["/odom"]["type"] == "nav_msgs/msg/Odometry"
        assert topics["/tf"]["messages"] > 0 and topics["/tf_static"]["messages"] >= 1
        assert topics["/never_published"]["absent"] is True
        assert record["size"] == path.stat().st_size and not record["cut_by_memory_bound"]


def test_dc_trigger_and_a_trigger_inside_the_window_give_one_file_with_both_reasons(run: Run) -> None:
    (record,) = [r for r in run.records if OPERATOR & reasons(r)]
    assert reasons(record) >= OPERATOR
    assert record["end"] == pytest.approx(record["triggers"][-1]["time"] + 1.5)
    assert (run.home / record["local_paths"]["mcap"]).is_file()


def test_the_files_are_read_by_the_mcap_package_with_their_schemas(run: Run) -> None:
    from mcap.reader import make_reader

    record = run.records[-1]
    with open(run.home / record["local_paths"]["mcap"], "rb") as stream:
        reader = make_reader(stream)
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        assert summary is not None
        topics = {channel.topic: summary.schemas[channel.schema_id].name for channel in summary.channels.values()}
        assert topics == {
            "/odom": "nav_msgs/msg/Odometry",
            "/tf": "tf2_msgs/msg/TFMessage",
            "/tf_static": "tf2_msgs/msg/TFMessage",
        }
