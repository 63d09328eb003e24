"""Two robots' DCs in one ROS domain, started with ``--namespace r1`` and ``--namespace r2``: each
delivers its own robot's records only.

The reported case: DC's default topics were absolute (/dc/measurement/<id>, /dc/group/<group>,
/dc/heartbeat), so both DCs published to the same topics and each destination_server took the other
robot's records too; a relative input (dc/measurement/who) under a namespace got nothing.
"""

from __future__ import annotations

import json
import re
import time
import urllib.request
from pathlib import Path
from typing import Any

import pytest

from tests.bringup_util import Bringup, dc

pytestmark = pytest.mark.e2e

ROBOTS = ("r1", "r2")
# Uptime records each robot delivers before the check: enough for the other robot's to have
# reached it too, had the topics been shared (both collect every 200 ms from the start).
RECORDS = 10
GROUPS = 3


def write_params(folder: Path, robot: str) -> Path:
    """One robot's file: the same topic names in both, only the robot_name differs."""
    folder.mkdir(parents=True, exist_ok=True)
    params = folder / "params.yaml"
    params.write_text(
        f"""measurement_server:
  ros__parameters:
    measurement_plugins: ["uptime"]
    http_server: true
    http_port: 0
    custom_str_params_list: ["robot_name"]
    custom_str_params:
      robot_name:
        name: "robot_name"
        value: "{robot}"
    run_id:
      counter_path: "{folder / "run_id"}"
    uptime:
      plugin: "dc_measurements/Uptime"
      polling_interval: 200
      tags: ["out"]
group_server:
  ros__parameters:
    groups: ["both"]
    both:
      inputs: ["dc/measurement/uptime"]
      sync_delay: 0.1
      tags: ["out"]
destination_server:
  ros__parameters:
    flb:
      storage_path: "{folder / "buffer"}"
    destination_plugins: ["out"]
    out:
      plugin: "dc_destinations/Stdout"
      inputs: ["dc/measurement/uptime", "dc/group/both", "dc/measurement/who"]
"""
    )
    return params


def robot_of(record: dict[str, Any]) -> str:
    """The robot a delivered record came from: its own robot_name, or its group member's, or who sent it."""
    if "who" in record:
        return str(record["who"])
    return str(record.get("robot_name") or record["uptime"]["robot_name"])


def handoff(run: Bringup) -> dict[str, Any]:
    """The `handoff` section of the robot's measurement_server metrics (its HTTP server logged its address)."""
    (address,) = {
        m.group(1) for line in run.stderr if "measurement_server" in line and (m := re.search(r"on (http://\S+)", line))
    }
    with urllib.request.urlopen(address + "metrics", timeout=5) as response:
        return dict(json.load(response)["handoff"])


@pytest.mark.usefixtures("bringup_mode")
def test_two_namespaced_dcs_in_one_domain_each_deliver_only_their_own_robots_records(tmp_path: Path) -> None:
    home = tmp_path / "home"
    r1 = Bringup(write_params(tmp_path / "r1", "r1"), home, args=["--namespace", "r1"])
    same_domain = {"ROS_DOMAIN_ID": str(r1.domain_id)}
    r2 = Bringup(write_params(tmp_path / "r2", "r2"), home, args=["--namespace", "r2"], env=same_domain)
    with r1, r2:
        runs = dict(zip(ROBOTS, (r1, r2), strict=True))
        for run in runs.values():
            run.wait_ready()
        for robot, run in runs.items():
            run.wait_records(RECORDS, 30, lambda r: r.get("name") == "uptime")
            run.wait_records(GROUPS, 30, lambda r: r.get("name") == "both")
            # A plain ROS 2 node of the robot, publishing on the relative name in the robot's namespace.
            published = dc(
                "pub", "dc/measurement/who", json.dumps({"who": robot, "tags": ["out"]}), "--namespace", robot,
                env=run.env,
            )  # fmt: skip
            assert published.returncode == 0, published.stderr
            assert f"published 1 record(s) on /{robot}/dc/measurement/who" in published.stdout
        for run in runs.values():
            run.wait_records(1, 30, lambda r: "who" in r)
        for robot, run in runs.items():
            delivered = run.records()
            robots = [robot_of(r) for r in delivered]
            assert robots == [robot] * len(delivered), f"{robot} delivered {robots.count('r1')} of r1's, " + (
                f"{robots.count('r2')} of r2's"
            )
            assert [r["who"] for r in delivered if "who" in r] == [robot]
            # Absolute names nowhere in the file: nothing to warn about.
            assert not any("is absolute" in line for line in run.stderr), "\n".join(run.stderr)
            info = [line for line in run.stderr if "measurement uptime (dc_measurements/Uptime) ->" in line]
            assert info and info[0].split("-> ")[1].startswith(f"/{robot}/dc/measurement/uptime"), info
            # The measurement server holds its records until its own destination_server acknowledges
            # them, on the hand-off topics of the namespace: acknowledged, they are not held.
            assert set(handoff(run)) == {f"/{robot}/dc/measurement/uptime"}
            deadline = time.monotonic() + 15
            while (held := handoff(run)[f"/{robot}/dc/measurement/uptime"])["unacked"] >= RECORDS // 2:
                assert time.monotonic() < deadline, f"{robot}'s records not acknowledged: {held}"
                time.sleep(0.2)
            assert held["dropped"] == 0
            # The lifecycle manager of each namespace hears its own servers' heartbeats only.
            active = dc("lifecycle", "is-active", "--namespace", robot, "--timeout", "10", env=run.env)
            assert active.returncode == 0, active.stdout + active.stderr


def test_absolute_dc_topics_under_a_namespace_are_honoured_and_warned_about_once_each(tmp_path: Path) -> None:
    params = tmp_path / "params.yaml"
    params.write_text(
        """measurement_server:
  ros__parameters:
    measurement_plugins: ["uptime", "cpu"]
    uptime:
      plugin: "dc_measurements/Uptime"
      topic_output: "/dc/measurement/uptime"
    cpu:
      plugin: "dc_measurements/Cpu"
group_server:
  ros__parameters:
    groups: ["g"]
    g:
      inputs: ["/dc/measurement/uptime", "dc/measurement/cpu"]
destination_server:
  ros__parameters:
    destination_plugins: ["out"]
    out:
      plugin: "dc_destinations/Stdout"
      inputs: ["/dc/measurement/uptime", "/dc/group/g", "/elsewhere"]
"""
    )
    namespaced = dc("validate", str(params), "--namespace", "r1")
    assert namespaced.returncode == 0, namespaced.stderr
    absolute = [line for line in namespaced.stderr.splitlines() if "is absolute" in line]
    # /dc/measurement/uptime is written three times, warned about once; /elsewhere is not DC's.
    assert len(absolute) == 2, namespaced.stderr
    assert absolute[0].startswith("warning: /dc/measurement/uptime is absolute: outside namespace /r1")
    assert "write dc/measurement/uptime (relative)" in absolute[0]
    assert absolute[1].startswith("warning: /dc/group/g is absolute")
    # The default output went to the namespace, the absolute input did not follow it.
    assert "destination_server.out.inputs: /dc/group/g is published by nothing" in namespaced.stderr
    # Without a namespace the same file is today's: no warning, every name under /dc/.
    plain = dc("validate", str(params))
    assert (
        plain.returncode == 0 and "is absolute" not in plain.stderr and "/dc/group/g is published" not in (plain.stderr)
    ), plain.stderr
