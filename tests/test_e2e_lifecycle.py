"""dc-bringup in a namespace, driven through its lifecycle manager's services with `dc lifecycle`."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from tests.bringup_util import Bringup, dc

pytestmark = pytest.mark.e2e

PARAMS = """
measurement_server:
  ros__parameters:
    measurement_plugins: ["uptime"]
    uptime:
      plugin: "dc_measurements/Uptime"
      polling_interval: 200
      topic_output: "dc/measurement/uptime"
      tags: ["out"]
destination_server:
  ros__parameters:
    flb:
      flush: 0.1
    destination_plugins: ["out"]
    out:
      plugin: "dc_destinations/Stdout"
      inputs: ["dc/measurement/uptime"]
"""


def test_pause_resume_reset_startup_and_shutdown_in_a_namespace(tmp_path: Path) -> None:
    params = tmp_path / "params.yaml"
    params.write_text(PARAMS)
    with Bringup(params, tmp_path / "home", args=["--namespace", "robot1", "--bond-timeout", "3"]) as bringup:
        bringup.wait_ready()
        bringup.wait_records(3)

        def lifecycle(command: str) -> str:
            result = dc("lifecycle", command, "--namespace", "robot1", env=bringup.env)
            assert result.returncode == (0 if command != "is-active" or "not" not in result.stdout else 1), result
            return result.stdout.strip()

        assert lifecycle("is-active").startswith("active")
        # Another namespace has no manager: a clear error, not a hang.
        other = dc("lifecycle", "is-active", "--namespace", "robot2", "--timeout", "2", env=bringup.env)
        assert other.returncode == 2 and "no lifecycle manager at /robot2/lifecycle_manager_dc" in other.stderr

        assert lifecycle("pause") == "pause: done"
        assert lifecycle("is-active").startswith("not active: servers inactive")
        paused_at = len(bringup.records())
        # Paused for longer than --bond-timeout: heartbeats go on, nothing is restarted, nothing published.
        deadline = time.monotonic() + 4.0
        bringup.wait_until(lambda: time.monotonic() > deadline, 10, "the pause to last")
        assert len(bringup.records()) <= paused_at + 1  # one record may have been on its way
        assert not [line for line in bringup.stderr if "restarting" in line], "\n".join(bringup.stderr)

        assert lifecycle("resume") == "resume: done"
        bringup.wait_records(paused_at + 3)

        assert lifecycle("reset") == "reset: done"
        assert lifecycle("is-active").startswith("not active: servers unconfigured")
        reset_at = len(bringup.records())
        assert lifecycle("startup") == "startup: done"
        bringup.wait_records(reset_at + 3)
        assert lifecycle("is-active").startswith("active")

        assert lifecycle("shutdown") == "shutdown: done"
        assert bringup.wait_exit(30) == 0
    # The servers' nodes were in the namespace, and so was the default delivery buffer.
    assert any("[robot1.destination_server]" in line for line in bringup.stderr)
    assert any("[robot1.measurement_server]" in line for line in bringup.stderr)
    assert list((tmp_path / "home").rglob("ns.robot1/delivery.sqlite3"))


def test_without_autostart_nothing_is_collected_until_startup(tmp_path: Path) -> None:
    params = tmp_path / "params.yaml"
    params.write_text(PARAMS)
    with Bringup(params, tmp_path / "home", args=["--no-autostart"]) as bringup:
        bringup.wait_stderr("DC is waiting for startup")
        result = dc("lifecycle", "is-active", env=bringup.env)
        assert result.returncode == 1 and "servers unconfigured" in result.stdout
        assert not bringup.records()
        assert dc("lifecycle", "startup", env=bringup.env).returncode == 0
        bringup.wait_records(2)
