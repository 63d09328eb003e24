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
import shutil
import subprocess
import sys
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
    assert launch_command(str(params)) == [python, "-m", "dc_bringup.launcher", str(params), "--log-level", "info"]
    assert launch_command(str(params), namespace="/robot1", use_sim_time="True", log_level="DEBUG") == [
        python,
        "-m",
        "dc_bringup.launcher",
        str(params),
        "--log-level",
        "debug",
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
