"""dc-bringup --single-process: every server in one process, watched by a supervisor that loads no ROS.

What a user relies on: the servers run and stop in order as with a process each, `dc lifecycle`
drives them, and the process is started again when it is killed, frozen, or its shared loop is stuck.
"""

from __future__ import annotations

import os
import signal
import textwrap
from pathlib import Path

import pytest

from tests.bringup_util import Bringup, dc, example_1_with_robot_name_from

pytestmark = pytest.mark.e2e

EXAMPLES = Path(__file__).resolve().parent.parent / "params" / "examples"
MODE = ["--single-process"]


def children(pid: int) -> list[int]:
    return [int(p) for p in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]


def cmdline(pid: int) -> list[str]:
    return [a for a in Path(f"/proc/{pid}/cmdline").read_bytes().decode().split("\0") if a]


def servers_pid(run: Bringup) -> int:
    """The pid of the servers' process that came up last, as the lifecycle manager logged it."""
    line = [s for s in run.stderr if "DC is up in one process (pid" in s][-1]
    return int(line.split("(pid ", 1)[1].split(")", 1)[0])


def test_every_server_runs_in_one_process_driven_by_dc_lifecycle_and_stops_in_order(tmp_path: Path) -> None:
    with Bringup(EXAMPLES / "example_1.yaml", tmp_path, args=MODE) as run:
        run.wait_ready()
        run.wait_records(2, timeout=60)
        assert run.process is not None
        (child,) = children(run.process.pid)
        assert cmdline(child)[1:4] == ["-m", "dc_bringup.single_process", str(EXAMPLES / "example_1.yaml")]
        assert servers_pid(run) == child
        assert any(f"measurement_server active (pid {child})" in s for s in run.stderr)
        assert any(f"destination_server active (pid {child})" in s for s in run.stderr)
        # The supervisor loads no ROS: it stays small beside the one process that does.
        rss_kb = {
            pid: int(
                next(x for x in Path(f"/proc/{pid}/status").read_text().splitlines() if x.startswith("VmRSS:")).split()[
                    1
                ]
            )
            for pid in (run.process.pid, child)
        }
        assert rss_kb[run.process.pid] < rss_kb[child] / 2, rss_kb

        paused = dc("lifecycle", "pause", env=run.env)
        # Fast DDS may print its own transport errors (shared-memory port locks) to stdout before the answer.
        assert paused.stdout.strip().splitlines()[-1] == "pause: done", paused
        assert dc("lifecycle", "is-active", env=run.env).stdout.startswith("not active: servers inactive")
        assert dc("lifecycle", "resume", env=run.env).stdout.strip() == "resume: done"
        before = len(run.records())
        run.wait_records(before + 2, timeout=30)
        assert run.stop() == 0
    stopped = [s for s in run.stderr if s.endswith(" stopped")]
    assert [s.rsplit("]: ", 1)[1] for s in stopped] == ["measurement_server stopped", "destination_server stopped"]


def test_the_process_is_restarted_after_kill_9_and_collection_resumes(tmp_path: Path) -> None:
    with Bringup(EXAMPLES / "example_1.yaml", tmp_path, args=[*MODE, "--bond-timeout", "3"]) as run:
        run.wait_records(2, timeout=60)
        os.kill(servers_pid(run), signal.SIGKILL)
        run.wait_stderr("the servers' process was killed by signal 9: restarting it", timeout=30)
        run.wait_until(lambda: sum("DC is up in one process" in s for s in run.stderr) == 2, 60, "the process up again")
        before = len(run.records())
        run.wait_records(before + 2, timeout=60)
    assert {r["run_id"] for r in run.records()} == {"1", "2"}, "the restarted servers are a new run"


def test_a_frozen_process_is_killed_and_restarted_by_the_supervisor(tmp_path: Path) -> None:
    with Bringup(EXAMPLES / "example_1.yaml", tmp_path, args=[*MODE, "--bond-timeout", "2"]) as run:
        run.wait_records(1, timeout=60)
        frozen = servers_pid(run)
        os.kill(frozen, signal.SIGSTOP)  # its own lifecycle manager is frozen too: only the supervisor can act
        run.wait_stderr("the servers' process sent nothing for 2 s (bond_timeout): killing it", timeout=30)
        run.wait_until(lambda: sum("DC is up in one process" in s for s in run.stderr) == 2, 60, "the process up again")
        assert servers_pid(run) != frozen
        before = len(run.records())
        run.wait_records(before + 1, timeout=30)


STUCK_PLUGIN = '''
"""A measurement whose collect() blocks the thread it runs on once a trigger file exists."""
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dc_core.measurement import Measurement


@dataclass(frozen=True, kw_only=True)
class StuckParams:
    pass


class Stuck(Measurement[StuckParams]):
    schema_file = None

    def collect(self) -> dict[str, Any] | None:
        while Path("stuck").exists():
            time.sleep(0.05)  # the loop the servers share turns no more
        return {"ok": True}
'''


def test_a_stuck_loop_is_noticed_by_the_heartbeats_and_the_process_restarted(tmp_path: Path) -> None:
    # A plugin package of the test's own, found through its entry point like any installed one.
    site = tmp_path / "site"
    site.mkdir()
    (site / "dc_test_stuck.py").write_text(STUCK_PLUGIN)
    dist = site / "dc_test_stuck-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: dc-test-stuck\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text("[dc.measurements]\ntest/Stuck = dc_test_stuck:Stuck\n")
    params = tmp_path / "params.yaml"
    params.write_text(
        textwrap.dedent("""
        measurement_server:
          ros__parameters:
            measurement_plugins: ["stuck"]
            stuck:
              plugin: "test/Stuck"
              polling_interval: 200
              tags: ["out"]
        destination_server:
          ros__parameters:
            flb:
              flush: 0.1
            destination_plugins: ["out"]
            out:
              plugin: "dc_destinations/Stdout"
              inputs: ["/dc/measurement/stuck"]
        """)
    )
    home = tmp_path / "home"
    env = {"PYTHONPATH": os.pathsep.join([str(site), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)}
    with Bringup(params, home, args=[*MODE, "--bond-timeout", "2"], env=env) as run:
        run.wait_records(2, timeout=60)
        stuck_pid = servers_pid(run)
        (home / "stuck").write_text("")
        run.wait_stderr("no heartbeat for", timeout=30)
        run.wait_stderr("the servers' process exited with code 75: restarting it", timeout=30)
        (home / "stuck").unlink()
        run.wait_until(lambda: sum("DC is up in one process" in s for s in run.stderr) == 2, 60, "the process up again")
        assert servers_pid(run) != stuck_pid
        before = len(run.records())
        run.wait_records(before + 2, timeout=30)


def test_a_process_that_never_came_up_is_not_restarted(tmp_path: Path) -> None:
    robot_file = tmp_path / "missing_robot_name"
    params = example_1_with_robot_name_from(robot_file, tmp_path / "params.yaml")
    with Bringup(params, tmp_path / "home", args=MODE) as run:
        code = run.wait_exit(60)
    assert code == 1, run.stderr
    assert any("measurement_server did not come up" in s or "configure failed" in s for s in run.stderr), run.stderr
    assert not any("restarting it" in s for s in run.stderr), run.stderr
