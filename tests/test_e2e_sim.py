"""The robot measurements end to end against `dc sim`'s ground truth, through dc-bringup with sim time.

The simulator writes what really happened (exact pose, path length, where it stopped) as JSON lines;
DC's records on stdout and the map files it saved must agree with them and with the grid it published.
"""

from __future__ import annotations

import bisect
import json
import math
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from dc_sim.warehouse import warehouse_grid
from tests.bringup_util import BIN, Bringup

pytestmark = pytest.mark.e2e

RATE = 4.0
DURATION_S = 60.0
POLL_MS = 500
# Below this commanded speed the robot stands (at a waypoint, or turning in place toward the next one).
STANDING_SPEED = 0.2

PARAMS = f"""
measurement_server:
  ros__parameters:
    measurement_plugins: ["distance_traveled", "position", "speed", "map", "stop_position"]
    condition_plugins: ["moving"]
    save_local_base_path: "maps_out/"
    moving:
      plugin: "dc_conditions/Moving"
      odom_topic: "/odom"
      speed_threshold: {STANDING_SPEED}
    distance_traveled:
      plugin: "dc_measurements/DistanceTraveled"
      global_frame: "map"
      robot_base_frame: "base_link"
      polling_interval: {POLL_MS}
      tags: ["out"]
    position:
      plugin: "dc_measurements/Position"
      global_frame: "map"
      robot_base_frame: "base_link"
      polling_interval: {POLL_MS}
      tags: ["out"]
    speed:
      plugin: "dc_measurements/Speed"
      polling_interval: {POLL_MS}
      tags: ["out"]
    map:
      plugin: "dc_measurements/Map"
      polling_interval: 2000
      save_path: "map/warehouse"
      tags: ["out"]
    stop_position:
      plugin: "dc_measurements/Position"
      global_frame: "map"
      robot_base_frame: "base_link"
      polling_interval: 250
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
               "/dc/measurement/map", "/dc/measurement/stop_position"]
"""


@dataclass
class SimRun:
    records: dict[str, list[dict[str, Any]]]
    truth: list[dict[str, Any]]
    home: Path

    def truth_at(self, t: float) -> dict[str, Any]:
        """The ground truth in effect at time t."""
        times = [line["t"] for line in self.truth]
        return self.truth[max(bisect.bisect_right(times, t) - 1, 0)]


def standing_episodes(truth: list[dict[str, Any]]) -> list[tuple[float, float]]:
    """Runs of the truth where the robot stands (slower than STANDING_SPEED), from the start."""
    episodes, start = [], None
    for line in truth:
        standing = abs(line["v"]) < STANDING_SPEED
        if standing and start is None:
            start = line["t"]
        elif not standing and start is not None:
            episodes.append((start, line["t"]))
            start = None
    if start is not None:
        episodes.append((start, truth[-1]["t"]))
    return episodes


@pytest.fixture(scope="module")
def sim_run(tmp_path_factory: pytest.TempPathFactory) -> SimRun:
    tmp = tmp_path_factory.mktemp("sim")
    params, truth_file = tmp / "robot.yaml", tmp / "truth.jsonl"
    params.write_text(PARAMS)
    with Bringup(params, tmp / "home", args=["--use-sim-time"]) as dc:
        dc.wait_ready()
        sim = subprocess.run(
            [
                *(str(BIN / "dc"), "sim", "--clock", "--rate", str(RATE), "--duration", str(DURATION_S)),
                *("--truth", str(truth_file), "--wait-subscribers", "20"),
            ],
            env=dc.env,
            capture_output=True,
            text=True,
            timeout=DURATION_S / RATE + 60,
        )
        assert sim.returncode == 0, sim.stderr
        truth = [json.loads(line) for line in truth_file.read_text().splitlines()]
        end = truth[-1]["t"]

        dc.wait_until(
            lambda: all(
                any(r["date"] >= end - POLL_MS / 1000 - 0.3 for r in dc.named(n))
                for n in ("distance_traveled", "position")
            ),
            30,
            "the last polls of the simulated time",
        )
        records = {n: dc.named(n) for n in ("distance_traveled", "position", "speed", "map", "stop_position")}
    return SimRun(records, truth, dc.home)


def test_distance_traveled_is_the_simulated_path_length(sim_run: SimRun) -> None:
    last = sim_run.records["distance_traveled"][-1]
    truth = sim_run.truth_at(last["date"])
    assert truth["distance"] > 5.0  # the robot went somewhere
    assert last["distance_traveled"] == pytest.approx(truth["distance"], rel=0.05)


def test_position_is_the_simulated_pose_in_the_map(sim_run: SimRun) -> None:
    for record in sim_run.records["position"][-5:]:
        truth = sim_run.truth_at(record["date"])["map"]
        # The robot drives at up to 0.5 m/s: the pose DC took may be one /tf update (0.04 s) older.
        assert math.hypot(record["x"] - truth["x"], record["y"] - truth["y"]) < 0.05
        assert abs(math.remainder(record["yaw"] - truth["yaw"], 2 * math.pi)) < 0.1


def test_speed_is_the_commanded_simulated_velocity(sim_run: SimRun) -> None:
    # A speed record is dated by its odometry's stamp, a simulation step; the truth has a line for most
    # steps (one per 0.1 s of 0.08 s steps), and the command jumps (0.5 to 0 when the robot turns): a record
    # is compared with the truth of its own step, never with an earlier line.
    by_ms = {round(line["t"] * 1000): line for line in sim_run.truth}
    matched = 0
    for record in sim_run.records["speed"]:
        truth = by_ms.get(round(record["date"] * 1000))
        if truth is None:
            continue
        matched += 1
        assert record["linear"]["x"] == pytest.approx(truth["v"], abs=1e-6)
        assert record["angular"]["z"] == pytest.approx(truth["w"], abs=1e-6)
    assert matched >= len(sim_run.records["speed"]) // 2 >= 30


def test_one_stop_record_per_standing_episode_where_the_robot_stood(sim_run: SimRun) -> None:
    # Moving starts "not moving" and needs a few odometry messages to see the robot go: whether a poll
    # falls in that first instant is a race, so the start is left out of the comparison.
    first_move = next(line["t"] for line in sim_run.truth if abs(line["v"]) >= STANDING_SPEED)
    episodes = [(a, b) for a, b in standing_episodes(sim_run.truth) if a > first_move]
    assert len(episodes) >= 3  # at least three waypoints in a minute
    stops = [r for r in sim_run.records["stop_position"] if r["date"] > first_move + 0.5]
    assert len(stops) == len(episodes), ([r["date"] for r in stops], episodes)
    for (start, end), record in zip(episodes, stops, strict=True):
        assert start - 0.5 <= record["date"] <= end + 0.5
        truth = sim_run.truth_at(record["date"])["map"]
        assert math.hypot(record["x"] - truth["x"], record["y"] - truth["y"]) < 0.05


def test_the_saved_map_is_the_published_grid_pixel_for_pixel(sim_run: SimRun) -> None:
    maps = sim_run.records["map"]
    assert len(maps) == 1  # the same grid is not saved twice
    record = maps[0]
    grid = warehouse_grid()
    assert (record["width"], record["height"]) == (grid.width, grid.height)
    cells = np.array(grid.data, dtype=np.int16).reshape(grid.height, grid.width)
    expected = np.full(cells.shape, 205, dtype=np.uint8)
    expected[(cells >= 0) & (cells <= 25)] = 254
    expected[(cells >= 65) & (cells <= 100)] = 0
    pgm = (sim_run.home / record["local_paths"]["pgm"]).read_bytes()
    header = f"P5\n{grid.width} {grid.height}\n255\n".encode()
    assert pgm.startswith(header)
    image = np.frombuffer(pgm[len(header) :], dtype=np.uint8).reshape(grid.height, grid.width)
    assert (image == expected[::-1]).all()
    assert record["origin"] == pytest.approx({"x": grid.origin.x, "y": grid.origin.y, "yaw": 0.0})


def test_the_robot_demo_runs_on_the_simulated_robot_as_the_readme_says(tmp_path: Path) -> None:
    """params/demos/robot_stdout.yaml with `dc sim --clock`: the group record and the saved map."""
    demo = Path(__file__).resolve().parent.parent / "params" / "demos" / "robot_stdout.yaml"
    with Bringup(demo, tmp_path, args=["--use-sim-time"]) as dc:
        dc.wait_ready()
        sim = subprocess.Popen(
            [str(BIN / "dc"), "sim", "--clock", "--rate", "4", "--duration", "40"],
            env=dc.env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        try:
            robot = dc.wait_records(2, 60, lambda r: r.get("name") == "robot")
            (saved,) = dc.wait_records(1, 60, lambda r: r.get("name") == "map")
            distance = dc.wait_records(2, 60, lambda r: r.get("name") == "distance_traveled")
        finally:
            sim.terminate()
            sim.wait(10)
    assert {"cmd_vel", "position", "speed"} <= set(robot[-1])
    assert robot[-1]["position"]["robot_name"] == "C3PO"
    assert distance[-1]["distance_traveled"] > 0
    pgm = tmp_path / saved["local_paths"]["pgm"]  # under var/dc/data/C3PO/<sim time's %Y/%m/%d/%H>/map/
    assert pgm.is_file() and "/C3PO/2023/11/14/" in str(pgm)
    assert saved["remote_paths"]["minio"]["png"].startswith("C3PO/2023/11/14/")
