"""dc-bringup's starts and restarts with the seed's examples, read as a user reads them: on stdout and
stderr. A run id per start; a configuration that cannot run stops before anything starts; a server
that is killed, cannot come back or hangs is restarted and collection resumes.

(Split from tests/test_e2e_examples.py so that pytest-xdist, which keeps a file in one worker, can run
the two halves side by side.)
"""

from __future__ import annotations

import os
import signal
from pathlib import Path

import pytest

from tests.bringup_util import REPO, Bringup, example_1_with_robot_name_from

EXAMPLES = REPO / "params" / "examples"
pytestmark = pytest.mark.e2e


def test_run_id_increments_between_starts(tmp_path: Path) -> None:
    for expected in ("1", "2"):
        with Bringup(EXAMPLES / "example_3.yaml", tmp_path) as run:
            records = run.wait_records(1, timeout=60)
        assert records[0]["run_id"] == expected


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("measurement_server:\n  ros__parameters:\n    measurement_plugins: [u\n", "invalid YAML"),
        (
            "measurement_server:\n  ros__parameters:\n    measurement_plugins: [u]\n    u:\n      plugin: dc_measurements/Nope\n",
            "measurement_server.u.plugin: unknown measurement plugin",
        ),
        (
            "measurement_server:\n  ros__parameters:\n    measurement_plugins: [u]\n    u:\n"
            "      plugin: dc_measurements/Uptime\n      polling_interval: fast\n",
            'measurement_server.u.polling_interval: expected an integer, got "fast"',
        ),
    ],
    ids=["invalid-yaml", "unknown-plugin", "wrong-type"],
)
@pytest.mark.usefixtures("bringup_mode")
def test_invalid_configuration_stops_before_anything_starts(tmp_path: Path, text: str, message: str) -> None:
    params = tmp_path / "p.yaml"
    params.write_text(text)
    with Bringup(params, tmp_path / "home") as run:
        code = run.wait_exit(30)
    assert code == 2
    assert any(message in line for line in run.stderr), run.stderr
    assert not any("active (pid" in line for line in run.stderr)


def test_killed_server_is_restarted_and_collection_resumes(tmp_path: Path) -> None:
    with Bringup(EXAMPLES / "example_1.yaml", tmp_path, args=["--bond-timeout", "3"]) as run:
        run.wait_records(2, timeout=60)
        line = next(s for s in run.stderr if "measurement_server active (pid" in s)
        pid = int(line.rsplit("pid ", 1)[1].rstrip(")"))
        os.kill(pid, signal.SIGKILL)
        run.wait_stderr("measurement_server exited with code -9: restarting it", timeout=30)
        before = len(run.records())
        run.wait_records(before + 2, timeout=60)
    run_ids = {r["run_id"] for r in run.records()}
    assert run_ids == {"1", "2"}, "the restarted server is a new run"


def test_a_server_that_does_not_come_back_is_restarted_again_until_it_does(tmp_path: Path) -> None:
    robot_file = tmp_path / "robot_name"
    robot_file.write_text("C3PO\n")
    params = example_1_with_robot_name_from(robot_file, tmp_path / "params.yaml")
    with Bringup(params, tmp_path / "home", args=["--bond-timeout", "2"]) as run:
        run.wait_records(1, timeout=60)
        line = next(s for s in run.stderr if "measurement_server active (pid" in s)
        robot_file.unlink()  # the restarted server cannot configure: it runs, heartbeats, and is not up
        os.kill(int(line.rsplit("pid ", 1)[1].rstrip(")")), signal.SIGKILL)
        run.wait_stderr("measurement_server could not be restarted; trying again in 2 s", timeout=60)
        robot_file.write_text("R2D2\n")
        run.wait_until(
            lambda: sum("measurement_server active (pid" in s for s in run.stderr) == 2, 60, "the server up again"
        )
        records = run.wait_records(1, predicate=lambda r: r.get("robot_name") == "R2D2", timeout=30)
    assert any("measurement_server did not come up: restarting it" in s for s in run.stderr)
    assert records[0]["name"] == "uptime"


def test_hung_server_is_detected_by_missing_heartbeat(tmp_path: Path) -> None:
    with Bringup(EXAMPLES / "example_1.yaml", tmp_path, args=["--bond-timeout", "2"]) as run:
        run.wait_records(1, timeout=60)
        line = next(s for s in run.stderr if "measurement_server active (pid" in s)
        pid = int(line.rsplit("pid ", 1)[1].rstrip(")"))
        os.kill(pid, signal.SIGSTOP)  # alive but silent: only the heartbeat can tell
        run.wait_stderr("measurement_server no heartbeat for", timeout=30)
        # Usually ~3 s. Once in this session's ~10 full runs the new process did not come up within
        # dc-bringup's 30 s, after which it starts another one: room for that second attempt.
        run.wait_until(
            lambda: sum("measurement_server active (pid" in s for s in run.stderr) == 2, 90, "the new process active"
        )
        before = len(run.records())
        run.wait_records(before + 1, timeout=30)
