"""Two namespaced `dc sim` robots in one ROS domain, each with a namespaced DC: every Position record
follows its own robot.

The robots' TF is in their namespaces (`/r1/tf`, `/r2/tf`), as in Nav2's multi-robot bringup, and
both use the same frame names (map, odom, base_link): a DC reading the other robot's TF, or both
robots' on a shared `/tf`, would report poses of the other robot or a mix. The two robots drive the
same route at different speeds, so their poses soon differ by metres.
"""

from __future__ import annotations

import bisect
import json
import math
import subprocess
from functools import partial
from pathlib import Path
from typing import Any

import pytest

from tests.bringup_util import BIN, Bringup

pytestmark = pytest.mark.e2e

# Simulated seconds per wall-clock second of each robot: r1 runs the route three times faster.
RATES = {"r1": 3.0, "r2": 1.0}
POLL_MS = 200
# Records taken while the two robots are at least this far apart (m), for each robot.
APART_M = 1.0
APART_RECORDS = 5
TF_REMAPS = ["--ros-args", "-r", "/tf:=tf", "-r", "/tf_static:=tf_static"]

PARAMS = f"""
measurement_server:
  ros__parameters:
    measurement_plugins: ["position"]
    position:
      plugin: "dc_measurements/Position"
      global_frame: "map"
      robot_base_frame: "base_link"
      polling_interval: {POLL_MS}
      tags: ["out"]
destination_server:
  ros__parameters:
    destination_plugins: ["out"]
    out:
      plugin: "dc_destinations/Stdout"
      inputs: ["dc/measurement/position"]
"""


def read_truth(path: Path) -> list[dict[str, Any]]:
    if not path.exists():
        return []
    text = path.read_text()
    return [json.loads(line) for line in text[: text.rfind("\n") + 1].splitlines()]


def pose_at(truth: list[dict[str, Any]], t: float) -> dict[str, float]:
    """The robot's map pose in effect at time t (the truth is written every 0.1 simulated s)."""
    times = [line["t"] for line in truth]
    pose: dict[str, float] = truth[max(bisect.bisect_right(times, t) - 1, 0)]["map"]
    return pose


def distance(record: dict[str, Any], pose: dict[str, float]) -> float:
    return math.hypot(record["x"] - pose["x"], record["y"] - pose["y"])


def apart(dcs: dict[str, Bringup], truths: dict[str, Path], robot: str) -> list[dict[str, Any]]:
    """The robot's Position records taken while the other robot was elsewhere, far from the other's pose."""
    other = next(r for r in RATES if r != robot)
    own, others = read_truth(truths[robot]), read_truth(truths[other])
    if not own or not others:
        return []
    return [
        r
        for r in dcs[robot].named("position")
        if own[0]["t"] <= r["date"] <= min(own[-1]["t"], others[-1]["t"])
        and distance(r, pose_at(others, r["date"])) >= APART_M
    ]


def test_two_namespaced_sim_robots_each_position_follows_its_own_robot(tmp_path: Path) -> None:
    params = tmp_path / "params.yaml"
    params.write_text(PARAMS)
    dcs = {
        robot: Bringup(params, tmp_path / robot, args=["--single-process", "--namespace", robot, *TF_REMAPS])
        for robot in RATES
    }
    domain = {"ROS_DOMAIN_ID": str(dcs["r1"].domain_id)}
    dcs["r2"].env.update(domain)
    truths = {robot: tmp_path / f"{robot}.truth.jsonl" for robot in RATES}
    sims: dict[str, subprocess.Popen[str]] = {}
    with dcs["r1"], dcs["r2"]:
        try:
            for dc in dcs.values():
                dc.wait_ready()
            for robot, rate in RATES.items():
                sims[robot] = subprocess.Popen(
                    [
                        *(str(BIN / "dc"), "sim", "--namespace", robot, "--rate", str(rate), "--loop"),
                        *("--camera-fps", "0", "--truth", str(truths[robot]), *TF_REMAPS),
                    ],
                    env=dcs[robot].env,
                    stdout=subprocess.DEVNULL,
                    stderr=subprocess.PIPE,
                    text=True,
                )

            for robot, dc in dcs.items():
                dc.wait_until(
                    partial(lambda robot: len(apart(dcs, truths, robot)) >= APART_RECORDS, robot),
                    30,
                    f"{robot}'s poses apart from the other robot's",
                )
        finally:
            for sim in sims.values():
                sim.terminate()
            for sim in sims.values():
                sim.wait(10)
        for sim in sims.values():
            assert sim.returncode == 0, sim.stderr.read() if sim.stderr else ""

    for robot, dc in dcs.items():
        own = read_truth(truths[robot])
        records = [r for r in dc.named("position") if own[0]["t"] <= r["date"] <= own[-1]["t"]]
        assert records, f"{robot}: no Position record while its sim ran"
        # Every pose is this robot's (up to a step of the sim at its speed, 0.02 s x 0.5 m/s x rate).
        wrong = [
            (r["date"], r["x"], r["y"], pose_at(own, r["date"]))
            for r in records
            if distance(r, pose_at(own, r["date"])) > 0.1
        ]
        assert not wrong, f"{robot}: Position records not at its own robot's pose: {wrong[:5]}"
        assert len(apart(dcs, truths, robot)) >= APART_RECORDS
