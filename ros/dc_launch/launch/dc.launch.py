"""Start DC (dc-bringup: every configured server and the lifecycle manager) from a ROS 2 launch file.

    ros2 launch dc_launch dc.launch.py params_file:=/path/to/dc.yaml namespace:=robot1 use_sim_time:=true

DC itself must be installed in the Python that runs `ros2 launch` (docs/bringup.md, "Using a ROS 2
installation instead of the wheels"): the command line is built by DC
(dc_bringup.launcher.launch_command), which checks the arguments first.
"""

import sys

from launch import LaunchContext, LaunchDescription
from launch.actions import DeclareLaunchArgument, ExecuteProcess, OpaqueFunction
from launch.substitutions import LaunchConfiguration

# dc-bringup stops the servers in order on SIGINT, each given up to --stop-timeout (15 s) to deliver
# what it holds: launch's default of 5 s before SIGTERM would cut that short.
STOP_GRACE_S = "60"


def _bringup(context: LaunchContext) -> list[ExecuteProcess]:
    try:
        from dc_bringup.launcher import launch_command
    except ImportError as exc:
        # The `ros2` script runs /usr/bin/python3, whatever venv is active.
        raise RuntimeError(
            f"DC is not installed in the Python running ros2 launch ({sys.executable}): install it there, "
            'or run launch with the Python of DC\'s venv: python3 "$(command -v ros2)" launch dc_launch ...'
        ) from exc

    def arg(name: str) -> str:
        return LaunchConfiguration(name).perform(context)

    command = launch_command(
        params_file=arg("params_file"),
        namespace=arg("namespace"),
        use_sim_time=arg("use_sim_time"),
        log_level=arg("log_level"),
    )
    return [ExecuteProcess(cmd=command, name="dc_bringup", output="screen", sigterm_timeout=STOP_GRACE_S)]


def generate_launch_description() -> LaunchDescription:
    return LaunchDescription(
        [
            DeclareLaunchArgument("params_file", description="DC parameter file (ROS 2 parameter YAML)"),
            DeclareLaunchArgument("namespace", default_value="", description="namespace of every DC node"),
            DeclareLaunchArgument(
                "use_sim_time", default_value="false", description="follow /clock (simulator, bag replay)"
            ),
            DeclareLaunchArgument("log_level", default_value="info", description="debug, info, warn, error or fatal"),
            OpaqueFunction(function=_bringup),
        ]
    )
