"""ros/dc_launch: the ament_python package whose dc.launch.py starts DC from a colcon workspace.

`launch` and `launch_ros` are not on PyPI (no ros-jazzy-launch wheel), so `ros2 launch` cannot run
here. What is tested instead: the package is one colcon and ament accept (package.xml, marker, the
files its setup installs where `ros2 launch dc_launch dc.launch.py` looks), the launch file declares
the documented arguments and hands them to DC's launch_command, and the command that builds starts
DC, which delivers, and stops it cleanly on the SIGINT launch sends at shutdown.
"""

from __future__ import annotations

import ast
import inspect
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from catkin_pkg.package import parse_package

from dc_bringup.launcher import launch_command
from tests.bringup_util import REPO, Bringup

PACKAGE = REPO / "ros" / "dc_launch"
LAUNCH_FILE = PACKAGE / "launch" / "dc.launch.py"
ARGUMENTS = {"params_file", "namespace", "use_sim_time", "log_level"}
PIP_OFFLINE = [sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation", "--no-index"]


def test_package_xml_is_a_valid_ament_python_package() -> None:
    package = parse_package(str(PACKAGE))
    package.validate()
    assert package.name == "dc_launch"
    assert package.get_build_type() == "ament_python"
    assert {dep.name for dep in package.exec_depends} >= {"launch", "dc_interfaces", "dc_lifecycle_interfaces"}
    assert (PACKAGE / "resource" / "dc_launch").is_file()


def test_setup_installs_what_ros2_launch_looks_for(tmp_path: Path) -> None:
    # As colcon's ament_python build does: setup.py installed into a prefix (here by pip, offline).
    source = shutil.copytree(PACKAGE, tmp_path / "src" / "dc_launch")
    prefix = tmp_path / "install"
    subprocess.run(
        [*PIP_OFFLINE, "--prefix", str(prefix), str(source)],
        check=True,
        timeout=120,
    )
    assert (prefix / "share" / "ament_index" / "resource_index" / "packages" / "dc_launch").is_file()
    assert (prefix / "share" / "dc_launch" / "package.xml").read_text() == (PACKAGE / "package.xml").read_text()
    assert (prefix / "share" / "dc_launch" / "launch" / "dc.launch.py").read_text() == LAUNCH_FILE.read_text()


def test_launch_file_declares_the_documented_arguments_and_passes_them_to_dc() -> None:
    tree = ast.parse(LAUNCH_FILE.read_text())
    calls = [
        (node.func.id, node)
        for node in ast.walk(tree)
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name)
    ]
    declared = {
        call.args[0].value
        for name, call in calls
        if name == "DeclareLaunchArgument" and isinstance(call.args[0], ast.Constant)
    }
    assert declared == ARGUMENTS
    (to_dc,) = [call for name, call in calls if name == "launch_command"]
    assert {keyword.arg for keyword in to_dc.keywords} == ARGUMENTS
    assert set(inspect.signature(launch_command).parameters) == ARGUMENTS | {"python"}


def test_launch_command_reads_launch_arguments_as_text(tmp_path: Path) -> None:
    params = tmp_path / "dc.yaml"
    params.write_text("measurement_server:\n  ros__parameters: {}\n")
    python = sys.executable
    dc = [python, "-m", "dc_bringup.launcher", str(params)]
    assert launch_command(str(params)) == [*dc, "--log-level", "info", "--stop-with-parent"]
    assert launch_command(str(params), namespace="/robot1", use_sim_time="True", log_level="DEBUG") == [
        *dc,
        "--log-level",
        "debug",
        "--stop-with-parent",
        "--namespace",
        "/robot1",
        "--use-sim-time",
    ]
    assert "--use-sim-time" not in launch_command(str(params), use_sim_time="false")
    with pytest.raises(ValueError, match=r"^params_file: required"):
        launch_command("")
    with pytest.raises(ValueError, match=r"^params_file: .*missing.yaml is not a file"):
        launch_command(str(tmp_path / "missing.yaml"))
    with pytest.raises(ValueError, match=r"^use_sim_time: 'maybe' is not a boolean"):
        launch_command(str(params), use_sim_time="maybe")
    with pytest.raises(ValueError, match=r"^log_level: 'verbose' is not one of debug, info, warn, error, fatal"):
        launch_command(str(params), log_level="verbose")


def test_the_command_the_launch_file_runs_starts_dc_and_stops_on_sigint(tmp_path: Path) -> None:
    params = REPO / "params" / "examples" / "example_1.yaml"
    command = launch_command(str(params), namespace="robot1", use_sim_time="false", log_level="info")
    with Bringup(params, tmp_path / "home", command=command) as run:
        run.wait_ready()
        assert run.wait_records(1, predicate=lambda r: r.get("name") == "uptime")
        # What ros2 launch does at shutdown (then SIGTERM after the launch file's STOP_GRACE_S).
        assert run.stop() == 0
    assert any("/robot1/" in line or "robot1." in line for line in run.stderr), run.stderr[-20:]


def test_dc_stops_in_order_when_launch_is_killed(tmp_path: Path) -> None:
    """launch killed, or given SIGTERM (docker stop), exits without stopping its children: with
    --stop-with-parent, which the launch file's command has, dc-bringup stops its servers in order."""
    params = REPO / "params" / "examples" / "example_1.yaml"
    command = launch_command(str(params), namespace="robot1")
    # The launcher's stand-in: starts the command, says its pid, waits to be killed.
    parent = (
        "import subprocess, sys, time\n"
        f"child = subprocess.Popen({command!r})\n"
        "print('child', child.pid, file=sys.stderr, flush=True)\n"
        "time.sleep(300)\n"
    )
    with Bringup(params, tmp_path / "home", command=[sys.executable, "-c", parent]) as run:
        child = int(run.wait_stderr("child ").split()[1])
        run.wait_ready()
        run.wait_records(1, predicate=lambda r: r.get("name") == "uptime")
        assert run.process is not None
        run.process.kill()
        run.wait_stderr("destination_server stopped (exit code 0)", 30)
        deadline = time.monotonic() + 30
        while Path(f"/proc/{child}").exists() and time.monotonic() < deadline:
            time.sleep(0.1)  # an orphan is reaped by init: no exit status to wait for here
        assert not Path(f"/proc/{child}").exists(), "dc-bringup outlived its launcher"
    assert any("measurement_server stopped (exit code 0)" in line for line in run.stderr)


def test_ros2_launch_runs_the_launch_file(tmp_path: Path) -> None:
    """With `launch` installed (a ROS installation; not the wheels, so skipped in DC's CI): the launch
    file run by launch's own LaunchService, as `ros2 launch dc_launch dc.launch.py` runs it, and
    stopped as Ctrl-C in a terminal stops it: SIGINT to launch's whole process group (launch then
    leaves the signal to its children rather than sending another)."""
    pytest.importorskip("launch", reason="launch is not on PyPI: only a ROS installation has it")
    params = REPO / "params" / "examples" / "example_1.yaml"
    arguments = {"params_file": str(params), "namespace": "robot1", "use_sim_time": "false", "log_level": "info"}
    script = tmp_path / "run_launch.py"
    script.write_text(
        "import os, sys\n"
        "from launch import LaunchService\n"
        "from launch.actions import IncludeLaunchDescription\n"
        "from launch.launch_description_sources import PythonLaunchDescriptionSource\n"
        "os.setpgrp()  # a terminal's foreground group of its own\n"
        "service = LaunchService(argv=[])\n"
        f"source = PythonLaunchDescriptionSource({str(LAUNCH_FILE)!r})\n"
        f"service.include_launch_description(IncludeLaunchDescription(source, launch_arguments={arguments!r}.items()))\n"
        "sys.exit(service.run())\n"
    )
    # Through Bringup: what launch prints is read as dc-bringup's own output is.
    with Bringup(params, tmp_path / "home", command=[sys.executable, str(script)]) as run:
        printed = lambda: run.stdout + run.stderr  # noqa: E731
        run.wait_until(lambda: any("DC is up" in line for line in printed()), 60, "DC up")
        run.wait_until(lambda: any('"name":"uptime"' in line for line in printed()), 30, "an uptime record")
        assert run.process is not None
        os.killpg(run.process.pid, signal.SIGINT)
        assert run.wait_exit(30) == 0
    assert any("[robot1.lifecycle_manager_dc]" in line for line in printed())
    assert any("measurement_server stopped (exit code 0)" in line for line in printed())
    assert any("destination_server stopped (exit code 0)" in line for line in printed())
