"""dc-bringup PARAMS: validate, start every configured server, manage them, stop them in order."""

from __future__ import annotations

import argparse
import os
import signal
import sys
from collections.abc import Sequence
from pathlib import Path

from dc_bringup.validate import SERVER_MODULES, check
from dc_core.native_stdout import python_only_stdout
from dc_core.private_files import use_private_umask
from dc_core.signals import StopRequest, wake_on_signals

LOG_LEVELS = ("debug", "info", "warn", "error", "fatal")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="dc-bringup", description="Start DC's servers for a parameter file and keep them running."
    )
    parser.add_argument(
        "params_file", help="ROS 2 parameter YAML (measurement_server, group_server, destination_server)"
    )
    parser.add_argument("--log-level", default="info", choices=LOG_LEVELS, help="log level of every server")
    parser.add_argument(
        "--bond-timeout",
        type=float,
        default=10.0,
        help="seconds without heartbeat before a server is restarted (default 10)",
    )
    parser.add_argument(
        "--stop-timeout",
        type=float,
        default=15.0,
        help="seconds each server gets to stop before it is killed (default 15)",
    )
    parser.add_argument(
        "--transition-timeout",
        type=float,
        default=None,
        help="seconds a lifecycle transition may take before the server is asked where it is "
        "(default destination_server's flb.grace + 30)",
    )
    parser.add_argument(
        "--namespace", default="", help="ROS namespace of every server and of the lifecycle manager (e.g. robot1)"
    )
    parser.add_argument(
        "--use-sim-time",
        action="store_true",
        help="every server follows /clock (a bag replay, a simulator); a server's own use_sim_time: true does too",
    )
    parser.add_argument(
        "--no-autostart",
        action="store_true",
        help="start the server processes but configure and activate them only on `dc lifecycle startup`",
    )
    parser.add_argument(
        "--single-process",
        action="store_true",
        help="run every server in one process with one loop (less memory and CPU, less isolation; docs/bringup.md)",
    )
    parser.add_argument("--validate-only", action="store_true", help="check the configuration and exit")
    parser.epilog = (
        "--ros-args ... (last, or ended by --): ROS arguments given to every server as to any ROS node: "
        "remaps (-r /tf:=tf), parameters (-p name:=value, -p node:name:=value, --params-file FILE, over the "
        "parameter file's), --log-level (docs/bringup.md)"
    )
    parser.add_argument(
        "--stop-with-parent",
        action="store_true",
        help="stop, as on SIGTERM, when the process that started dc-bringup exits, even killed (dc.launch.py sets it)",
    )
    return parser


def dc_namespace(args: argparse.Namespace) -> str:
    """The namespace of the servers: --namespace, or a ``-r __ns:=`` of the ROS arguments."""
    from dc_core.ros_args import namespace_remap

    return args.namespace if args.namespace.strip("/") else (namespace_remap(args.ros_args) or "")


_TRUE = ("true", "1", "yes", "on")
_FALSE = ("false", "0", "no", "off", "")


def launch_command(
    params_file: str,
    namespace: str = "",
    use_sim_time: str = "false",
    log_level: str = "info",
    python: str = sys.executable,
) -> list[str]:
    """The dc-bringup command line for the arguments of the ament package's dc.launch.py (ros/dc_launch).

    Launch arguments arrive as text (``use_sim_time:=True``), so they are read here, where a wrong one
    is refused with its name before any process starts. The command runs DC with the interpreter that
    imported it: the one that has DC installed, whatever ``dc-bringup`` is first on PATH.
    """
    if not params_file.strip():
        raise ValueError("params_file: required (a DC parameter file, e.g. params_file:=/path/to/dc.yaml)")
    path = Path(params_file).expanduser().resolve()
    if not path.is_file():
        raise ValueError(f"params_file: {path} is not a file")
    sim = use_sim_time.strip().lower()
    if sim not in _TRUE + _FALSE:
        raise ValueError(f"use_sim_time: {use_sim_time!r} is not a boolean (true or false)")
    level = log_level.strip().lower()
    if level not in LOG_LEVELS:
        raise ValueError(f"log_level: {log_level!r} is not one of {', '.join(LOG_LEVELS)}")
    # launch leaves its children running when it is killed or gets SIGTERM (docker stop, a supervisor):
    # DC then stops in order instead of living on without it.
    command = [python, "-m", "dc_bringup.launcher", str(path), "--log-level", level, "--stop-with-parent"]
    if namespace.strip("/ "):
        command += ["--namespace", namespace.strip()]
    if sim in _TRUE:
        command.append("--use-sim-time")
    return command


def main(argv: Sequence[str] | None = None) -> int:
    from dc_core.ros_args import split_ros_args

    own, ros_args = split_ros_args(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(own)
    args.ros_args = ros_args
    if args.stop_with_parent:
        from dc_bringup.processes import die_with_parent

        parent = os.getppid()
        die_with_parent()
        if os.getppid() != parent:  # gone before it could be watched
            return 0
    # Before anything is written: the servers, ffmpeg and rclpy's log files inherit it (dc_core.private_files).
    use_private_umask()
    # Before rclpy starts: standard output carries the servers' records, not Fast DDS's own lines.
    python_only_stdout()
    params_file = str(Path(args.params_file).resolve())
    if args.single_process and not args.validate_only:
        # The servers' process checks the file: parsing it imports every configured plugin's module,
        # which the supervisor, meant to stay small, must not.
        os.environ.setdefault("RCUTILS_COLORIZED_OUTPUT", "0")
        from dc_bringup.single_process import supervise

        return supervise(args, params_file)
    report, error = check(params_file, dc_namespace(args), ros_args)
    if report is None:
        print(f"dc-bringup: invalid configuration: {error}", file=sys.stderr)
        return 2
    for note in report.notes:
        print(f"dc-bringup: {note}", file=sys.stderr)
    for warning in report.warnings:
        print(f"dc-bringup: warning: {warning}", file=sys.stderr)
    if args.validate_only:
        return 0
    os.environ.setdefault("RCUTILS_COLORIZED_OUTPUT", "0")

    # The handler only sets a flag and writes the wake-up socket: safe however many signals come (dc_core.signals).
    stop = StopRequest()
    stop.install()

    # Imported late: validating a configuration must not need a ROS context.
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    from dc_bringup.manager import LifecycleManager, default_transition_timeout
    from dc_bringup.processes import ServerProcess

    try:
        # The ROS arguments too: rcl refuses here, before any server starts, what it would refuse in each
        # (a -p list of mixed types), and the manager is in the namespace a -r __ns:= gives them.
        manager_args = ["--ros-args", "--log-level", args.log_level, *ros_args]
        rclpy.init(args=manager_args, signal_handler_options=SignalHandlerOptions.NO)
    except Exception as exc:  # rclpy's RCLError, UnknownROSArgsError: both say which argument
        print(f"dc-bringup: invalid --ros-args: {exc}", file=sys.stderr)
        return 2
    from dc_core.topics import ros_namespace

    namespace = ros_namespace(dc_namespace(args)) if dc_namespace(args).strip("/") else ""
    servers = [
        ServerProcess(name, SERVER_MODULES[name], params_file, args.log_level, namespace, args.use_sim_time, ros_args)
        for name in SERVER_MODULES
        if name in report.servers
    ]
    manager = LifecycleManager(
        servers,
        bond_timeout=args.bond_timeout,
        namespace=namespace,
        transition_timeout=args.transition_timeout or default_transition_timeout(report.configs),
    )
    manager.stop_timeout = args.stop_timeout  # an unhealthy server is stopped in order before its restart
    # A signal, or a server process exiting, wakes the watch at once rather than at its next period.
    signal.signal(signal.SIGCHLD, lambda signum, frame: None)
    wake_on_signals(manager.wake, stop, manager.supervisor)
    if args.no_autostart:
        manager.target_state = "unconfigured"
    code = 0
    try:
        if not manager.start_all():
            code = 1
        else:
            if args.no_autostart:
                manager.get_logger().info(
                    "DC is waiting for startup (dc lifecycle startup): " + ", ".join(s.name for s in servers)
                )
            else:
                manager.get_logger().info("DC is up: " + ", ".join(s.name for s in servers))
            while not stop.is_set() and not manager.shutdown_requested:
                manager.wait_for_work()
                manager.run_commands()
                manager.check_bonds()
    finally:
        manager.shut_down(args.stop_timeout)
        manager.destroy_node()
        rclpy.shutdown()
    return code


if __name__ == "__main__":
    sys.exit(main())
