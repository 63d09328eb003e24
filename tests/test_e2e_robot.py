"""The robot measurements end to end on real robot data: recorded bags replayed through dc-bringup with sim time.

The reference figures come from the bags themselves (read here with rosbags, without ROS): the
odometry's path length, its final pose, its twists, and the stop episodes that Moving's hysteresis
sees in its speeds. DC's records on stdout must agree with them.
"""

from __future__ import annotations

import bisect
import itertools
import math
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from dc_conditions.moving import MovingHysteresis
from tests.bringup_util import BIN, Bringup

BAGS = Path(__file__).parent / "data" / "bags"
RATE = 4.0
POLL_MS = 250
# Two odometry periods (5 Hz) plus the clock's lag: how far from a Speed record's date its message may be.
SPEED_MATCH_S = 0.5
# Moving's hysteresis for these bags: the Neato drives ~1 m legs in 12-13 odometry messages (5 Hz), fewer
# than the default count_hysteresis (5) needs to switch from a full count_limit (8) of the other sign.
SPEED_THRESHOLD, COUNT_LIMIT, COUNT_HYSTERESIS = 0.2, 5, 3

pytestmark = pytest.mark.e2e


@dataclass(frozen=True)
class OdometrySample:
    t: float  # header stamp, s
    x: float
    y: float
    yaw: float
    vx: float
    vy: float
    wz: float


def bag_odometry(bag: Path) -> list[OdometrySample]:
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    typestore = get_typestore(Stores.ROS2_HUMBLE)
    samples = []
    with Reader(bag) as reader:
        odom = [c for c in reader.connections if c.topic == "/odom"]
        for connection, _, raw in reader.messages(connections=odom):
            m: Any = typestore.deserialize_cdr(raw, connection.msgtype)
            q = m.pose.pose.orientation
            samples.append(
                OdometrySample(
                    m.header.stamp.sec + m.header.stamp.nanosec * 1e-9,
                    m.pose.pose.position.x,
                    m.pose.pose.position.y,
                    math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z)),
                    m.twist.twist.linear.x,
                    m.twist.twist.linear.y,
                    m.twist.twist.angular.z,
                )
            )
    return sorted(samples, key=lambda s: s.t)


def path_length(samples: list[OdometrySample]) -> float:
    return sum(math.hypot(b.x - a.x, b.y - a.y) for a, b in itertools.pairwise(samples))


def stop_episodes(samples: list[OdometrySample]) -> list[tuple[float, float]]:
    """(start, end) of each run of "not moving" in Moving's hysteresis over the odometry, the first from the start."""
    hysteresis = MovingHysteresis(SPEED_THRESHOLD, COUNT_LIMIT, COUNT_HYSTERESIS)
    episodes: list[tuple[float, float]] = []
    start: float | None = samples[0].t
    for s in samples:
        moving = hysteresis.update(math.hypot(s.vx, s.vy))
        if moving and start is not None:
            episodes.append((start, s.t))
            start = None
        elif not moving and start is None:
            start = s.t
    if start is not None:
        episodes.append((start, samples[-1].t))
    return episodes


PARAMS = f"""
measurement_server:
  ros__parameters:
    measurement_plugins: ["distance_traveled", "position", "speed", "stop_position"]
    condition_plugins: ["moving"]
    moving:
      plugin: "dc_conditions/Moving"
      odom_topic: "/odom"
      speed_threshold: {SPEED_THRESHOLD}
      count_limit: {COUNT_LIMIT}
      count_hysteresis: {COUNT_HYSTERESIS}
    distance_traveled:
      plugin: "dc_measurements/DistanceTraveled"
      global_frame: "odom"
      robot_base_frame: "base_footprint"
      polling_interval: {POLL_MS}
      tags: ["out"]
    position:
      plugin: "dc_measurements/Position"
      global_frame: "odom"
      robot_base_frame: "base_footprint"
      polling_interval: {POLL_MS}
      tags: ["out"]
    speed:
      plugin: "dc_measurements/Speed"
      polling_interval: {POLL_MS}
      tags: ["out"]
    stop_position:
      plugin: "dc_measurements/Position"
      global_frame: "odom"
      robot_base_frame: "base_link"
      polling_interval: {POLL_MS}
      if_none_conditions: ["moving"]
      condition_max_measurements: 1
      tags: ["out"]
destination_server:
  ros__parameters:
    flb:
      flush: 0.2
    destination_plugins: ["out"]
    out:
      plugin: "dc_destinations/Stdout"
      inputs: ["/dc/measurement/distance_traveled", "/dc/measurement/position", "/dc/measurement/speed",
               "/dc/measurement/stop_position"]
"""


@dataclass
class Replayed:
    records: dict[str, list[dict[str, Any]]]
    odometry: list[OdometrySample]
    stderr: list[str]


def replay_through_dc(bag: Path, tmp_path: Path) -> Replayed:
    params = tmp_path / "robot.yaml"
    params.write_text(PARAMS)
    odometry = bag_odometry(bag)
    end = odometry[-1].t
    with Bringup(params, tmp_path / "home", args=["--use-sim-time"]) as dc:
        dc.wait_ready()
        replay = subprocess.run(
            # DistanceTraveled and the two Positions listen to /tf; Speed and Moving to /odom.
            [str(BIN / "dc"), "replay", str(bag), "--rate", str(RATE), "--wait-for", "/tf=3", "/odom=2"],
            env=dc.env,
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert replay.returncode == 0, replay.stderr
        # Simulated time stops with the bag: the last polls are those due before its end.
        last_poll = end - POLL_MS / 1000.0

        dc.wait_until(
            lambda: all(
                any(r["date"] >= last_poll - 0.3 for r in dc.named(n)) for n in ("distance_traveled", "position")
            ),
            30,
            "the last polls of the bag's time",
        )
        records = {name: dc.named(name) for name in ("distance_traveled", "position", "speed", "stop_position")}
        stderr = list(dc.stderr)
    assert all("neato2_interfaces" in line for line in replay.stderr.splitlines() if "WARN" in line)
    return Replayed(records, odometry, stderr)


def pose_at(odometry: list[OdometrySample], t: float) -> OdometrySample:
    """The odometry sample in effect at time t (the newest with a stamp at or before it)."""
    index = bisect.bisect_right([s.t for s in odometry], t) - 1
    return odometry[max(index, 0)]


@pytest.fixture(scope="module")
def drive_square(tmp_path_factory: pytest.TempPathFactory) -> Replayed:
    return replay_through_dc(BAGS / "cp24_drive_square", tmp_path_factory.mktemp("square"))


@pytest.fixture(scope="module")
def obstacle_avoider(tmp_path_factory: pytest.TempPathFactory) -> Replayed:
    return replay_through_dc(BAGS / "cp24_obstacle-avoider", tmp_path_factory.mktemp("avoider"))


@pytest.fixture(params=["drive_square", "obstacle_avoider"])
def replayed(request: pytest.FixtureRequest) -> Replayed:
    result: Replayed = request.getfixturevalue(request.param)
    return result


def test_records_are_dated_in_the_bags_time(replayed: Replayed) -> None:
    start, end = replayed.odometry[0].t, replayed.odometry[-1].t
    for name in ("distance_traveled", "position", "speed"):
        dates = [r["date"] for r in replayed.records[name]]
        assert dates, name
        assert start - 1.0 <= min(dates) and max(dates) <= end + 0.5, name


def test_distance_traveled_is_the_odometry_path_length(replayed: Replayed) -> None:
    reference = path_length(replayed.odometry)  # 3.57 m and 6.37 m (SOURCE.md)
    totals = [r["distance_traveled"] for r in replayed.records["distance_traveled"]]
    assert totals == sorted(totals)  # cumulative: it never goes down
    assert totals[-1] == pytest.approx(reference, rel=0.05)


def test_position_is_the_odometry_pose(replayed: Replayed) -> None:
    last = replayed.records["position"][-1]
    # The pose at the record's time; the square's robot stands at the end, so that is its final pose too.
    truth = pose_at(replayed.odometry, last["date"])
    assert math.hypot(last["x"] - truth.x, last["y"] - truth.y) < 0.05
    assert abs(math.remainder(last["yaw"] - truth.yaw, 2 * math.pi)) < 0.05


def test_final_position_of_the_square(drive_square: Replayed) -> None:
    last, final = drive_square.records["position"][-1], drive_square.odometry[-1]
    assert math.hypot(last["x"] - final.x, last["y"] - final.y) < 0.05


def test_speed_is_the_odometry_twist(replayed: Replayed) -> None:
    speeds = replayed.records["speed"]
    assert len(speeds) > 0.5 * (replayed.odometry[-1].t - replayed.odometry[0].t) * 1000 / POLL_MS
    twists = {(round(s.vx, 9), round(s.wz, 9)) for s in replayed.odometry}
    for record in speeds:
        assert (round(record["linear"]["x"], 9), round(record["angular"]["z"], 9)) in twists
        # A message of the poll's moment: /clock and /odom reach DC on two paths (its executor and its
        # intake), so at 4x the bag's pace the clock can be a few tens of ms of bag time behind or ahead.
        near = [s for s in replayed.odometry if abs(s.t - record["date"]) <= SPEED_MATCH_S]
        assert any(record["linear"]["x"] == s.vx and record["angular"]["z"] == s.wz for s in near), record
        assert record["computed"] == pytest.approx(math.hypot(record["linear"]["x"], record["linear"]["y"]))


def test_a_moving_gated_measurement_publishes_once_per_stop_episode(drive_square: Replayed) -> None:
    episodes = stop_episodes(drive_square.odometry)
    assert len(episodes) == 5  # at the start, after each of the 4 legs
    stops = drive_square.records["stop_position"]
    assert len(stops) == len(episodes), [r["date"] for r in stops]
    for (start, end), record in zip(episodes, stops, strict=True):
        assert start - 0.5 <= record["date"] <= end + 0.5
        truth = pose_at(drive_square.odometry, record["date"])
        # base_link is 0 to a few cm from base_footprint (static transform): the stop's place.
        assert math.hypot(record["x"] - truth.x, record["y"] - truth.y) < 0.1


def test_mcap_bags_replay_too(tmp_path: Path) -> None:
    from rosbags.rosbag2 import Reader, StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    typestore = get_typestore(Stores.ROS2_JAZZY)
    source, target = BAGS / "cp24_drive_square", tmp_path / "square_mcap"
    with Reader(source) as reader, Writer(target, version=8, storage_plugin=StoragePlugin.MCAP) as writer:
        wanted = [c for c in reader.connections if c.topic in ("/odom", "/tf", "/tf_static")]
        out: dict[str, Any] = {}
        for c in wanted:  # a topic recorded from two publishers is one connection of the new bag
            if c.topic not in out:
                # The old bag holds no type hashes: they come from Jazzy's definitions.
                out[c.topic] = writer.add_connection(
                    c.topic,
                    c.msgtype,
                    typestore=typestore,
                    offered_qos_profiles=getattr(c.ext, "offered_qos_profiles", ()),
                )
        for connection, t, raw in reader.messages(connections=wanted):
            writer.write(out[connection.topic], t, raw)
    replayed = replay_through_dc(target, tmp_path)
    totals = [r["distance_traveled"] for r in replayed.records["distance_traveled"]]
    assert totals[-1] == pytest.approx(path_length(replayed.odometry), rel=0.05)
