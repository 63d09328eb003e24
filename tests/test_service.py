"""DC as a systemd service (issue 30, item 10): the unit `dc service install` writes is one systemd accepts
(`systemd-analyze verify`), and its command line, run as systemd would run it (the environment file's
variables and the unit's Environment=, SIGTERM to stop), starts DC, delivers, and stops with exit 0; an
environment file without a secret the parameter file needs ends with the exit status the unit does not
restart on.

There is no running systemd here (PID 1 is not systemd, so no `systemd-run`): the unit's [Service]
section is read and its ExecStart run by the test, as the supervisor.
"""

from __future__ import annotations

import os
import shlex
import shutil
import signal
import stat
import subprocess
from pathlib import Path

import pytest

from tests.bringup_util import Bringup, dc

PARAMS = """\
measurement_server:
  ros__parameters:
    measurement_plugins: ["site"]
    site:
      plugin: "dc_measurements/Dummy"
      record: '{"site": "${DC_SITE}"}'
      polling_interval: 500
      tags: ["stdout"]
destination_server:
  ros__parameters:
    destination_plugins: ["stdout"]
    stdout:
      plugin: "dc_destinations/Stdout"
      inputs: ["/dc/measurement/site"]
"""


def service_section(unit: str) -> dict[str, list[str]]:
    """The [Service] section's settings, each key's values in order (systemd allows a key many times)."""
    settings: dict[str, list[str]] = {}
    section = ""
    for line in unit.splitlines():
        line = line.strip()
        if line.startswith("[") and line.endswith("]"):
            section = line[1:-1]
        elif section == "Service" and line and not line.startswith("#"):
            key, _, value = line.partition("=")
            settings.setdefault(key, []).append(value)
    return settings


def environment_of(settings: dict[str, list[str]]) -> dict[str, str]:
    """What systemd adds to the service's environment: the EnvironmentFile's lines, then Environment=."""
    env: dict[str, str] = {}
    for path in settings.get("EnvironmentFile", []):
        for line in Path(path.lstrip("-")).read_text().splitlines():
            if line.strip() and not line.lstrip().startswith("#"):
                key, _, value = line.partition("=")
                env[key.strip()] = value.strip()
    for value in settings.get("Environment", []):
        env.update(item.split("=", 1) for item in shlex.split(value))  # type: ignore[misc]
    return env


def as_systemd_would_run(
    service: tuple[Path, Path, Path], env_file_text: str
) -> tuple[list[str], dict[str, list[str]], dict[str, str]]:
    """The unit's ExecStart, its [Service] settings and the environment systemd adds, with this environment file."""
    _, unit_path, env_file = service
    env_file.write_text(env_file_text)
    settings = service_section(unit_path.read_text())
    (command,) = settings["ExecStart"]
    return shlex.split(command), settings, environment_of(settings)


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path]:
    """(parameter file, unit, environment file) of `dc service install` run into a folder of the test."""
    folder = tmp_path_factory.mktemp("service")
    params = folder / "robot.yaml"
    params.write_text(PARAMS)
    env_file = folder / "etc" / "dc-test.env"
    made = dc(
        "service", "install", str(params), "--name", "dc-test", "--unit-dir", str(folder), "--env-file", str(env_file)
    )
    assert made.returncode == 0, made.stderr
    assert f"wrote {env_file} (mode 600): set DC_SITE there" in made.stdout
    return params, folder / "dc-test.service", env_file


def test_the_unit_restarts_on_failure_logs_to_the_journal_and_keeps_secrets_in_a_600_file(
    service: tuple[Path, Path, Path],
) -> None:
    params, unit_path, env_file = service
    settings = service_section(unit_path.read_text())
    assert settings["Restart"] == ["on-failure"] and settings["RestartPreventExitStatus"] == ["2"]
    assert settings["StandardOutput"] == settings["StandardError"] == ["journal"]
    assert settings["EnvironmentFile"] == [str(env_file)]
    assert stat.S_IMODE(env_file.stat().st_mode) == 0o600
    assert "# DC_SITE=" in env_file.read_text()
    # The environment file is the user's once written: installing again leaves it alone.
    env_file.write_text("DC_SITE=dock-3\n")
    again = dc(
        "service",
        "install",
        str(params),
        "--name",
        "dc-test",
        "--unit-dir",
        str(unit_path.parent),
        "--env-file",
        str(env_file),
    )
    assert again.returncode == 0 and "dc-test.env" not in again.stdout
    printed = dc("service", "install", str(params), "--name", "dc-test", "--env-file", str(env_file), "--print")
    assert printed.stdout == unit_path.read_text()
    assert env_file.read_text() == "DC_SITE=dock-3\n"


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze is not installed")
def test_systemd_analyze_verify_accepts_the_unit(service: tuple[Path, Path, Path]) -> None:
    _, unit_path, _ = service
    verified = subprocess.run(["systemd-analyze", "verify", str(unit_path)], capture_output=True, text=True)
    assert verified.returncode == 0, verified.stderr
    # Warnings (an unknown key, a bad value) do not change the exit code: they name the unit's file.
    assert unit_path.name not in verified.stderr, verified.stderr


def test_its_exec_start_runs_delivers_and_stops_with_exit_0_on_sigterm(
    service: tuple[Path, Path, Path], tmp_path: Path
) -> None:
    command, settings, env = as_systemd_would_run(service, "DC_SITE=dock-3\n")
    ros_logs = tmp_path / "ros-log"
    env["ROS_LOG_DIR"] = str(ros_logs)
    with Bringup(service[0], tmp_path / "home", command=command, env=env) as run:
        assert run.wait_records(1, timeout=60)[0]["site"] == "dock-3"
        assert run.process is not None
        run.process.send_signal(signal.SIGTERM)  # KillMode=mixed: the main process alone gets it
        assert run.wait_exit(float(settings["TimeoutStopSec"][0])) == 0, "\n".join(run.stderr[-30:])
    # The journal is the only log: ROS's own log files (which nothing rotates) are off.
    assert not ros_logs.exists() or not any(ros_logs.rglob("*.log"))


def test_a_missing_secret_ends_with_the_status_the_unit_does_not_restart_on(service: tuple[Path, Path, Path]) -> None:
    command, settings, env = as_systemd_would_run(service, "# DC_SITE=\n")
    run = subprocess.run(
        command,
        env={**os.environ, **env},
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert str(run.returncode) in settings["RestartPreventExitStatus"]
    assert "measurement_server.site.record: environment variable DC_SITE is not set" in run.stderr
