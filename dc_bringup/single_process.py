"""dc-bringup --single-process: every server of a parameter file in one process, as the original's component container.

The process (``python -m dc_bringup.single_process PARAMS``) holds each configured server's node,
all served by one main loop (:class:`dc_core.lifecycle.ServerLoop` over their intakes), and the
lifecycle manager on a thread of its own. The manager does what it does for server processes: brings
the servers up in order, serves ``manage_nodes`` and ``is_active``, watches the heartbeats. The
servers keep their lifecycle services, heartbeats, buffers and counters.

What the manager cannot do here is restart one server: the servers share one loop, so one that stops
beating means the loop is stuck. The process then exits with :data:`EXIT_RESTART`, and dc-bringup —
reduced to a small supervisor that never loads ROS (:func:`supervise`) — starts it again, as it does
after a crash or a kill -9. Records wait in the destinations' disk buffers meanwhile.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from typing import Any

from dc_bringup.processes import die_with_parent
from dc_bringup.validate import SERVER_MODULES, check

# The process asks its supervisor for a restart (EX_TEMPFAIL): a server stopped beating.
EXIT_RESTART = 75
# What the process writes on the supervisor's pipe once every server is up.
READY = b"up\n"
# Waits between restarts of a process that keeps failing: doubling from the first, up to the last.
FIRST_RETRY_DELAY_S = 1.0
MAX_RETRY_DELAY_S = 60.0
# A process that stayed up this long is healthy again: its next failure restarts it at once.
HEALTHY_AFTER_S = 60.0

_SERVER_CLASSES = {
    "destination_server": "DestinationServer",
    "group_server": "GroupServer",
    "image_services": "ImageServices",
    "measurement_server": "MeasurementServer",
}


class InProcessServer:
    """A server node of this process, as the lifecycle manager sees a server it manages."""

    def __init__(self, name: str) -> None:
        self.name = name

    @property
    def pid(self) -> int:
        return os.getpid()

    def start(self) -> None:
        """The node exists from the process' start: nothing to launch."""

    def running(self) -> bool:
        return True

    def exit_code(self) -> int | None:
        return None

    def kill(self) -> None:
        # Called before a restart: only a new process can bring back a loop that is stuck.
        sys.stderr.write(f"[dc-bringup] {self.name} must be restarted: restarting every server's process\n")
        sys.stderr.flush()
        os._exit(EXIT_RESTART)

    def stop(self, timeout: float) -> int | None:
        return None


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="dc_bringup.single_process")
    parser.add_argument("params_file")
    parser.add_argument("--log-level", default="info")
    parser.add_argument("--bond-timeout", type=float, default=10.0)
    parser.add_argument("--namespace", default="")
    parser.add_argument("--use-sim-time", action="store_true")
    parser.add_argument("--no-autostart", action="store_true")
    parser.add_argument("--ready-fd", type=int, default=-1, help="pipe on which to say that every server is up")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    report, error = check(args.params_file)
    if report is None:
        print(f"dc-bringup: invalid configuration: {error}", file=sys.stderr)
        return 2

    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from rclpy.signals import SignalHandlerOptions

    from dc_bringup.manager import LifecycleManager
    from dc_core.lifecycle import ServerLoop, ros_namespace
    from dc_core.signals import wake_on_signals

    namespace = ros_namespace(args.namespace) if args.namespace.strip("/") else ""
    ros_args = ["--ros-args", "--log-level", args.log_level]
    if namespace:
        ros_args += ["-r", f"__ns:={namespace}"]
    rclpy.init(args=ros_args, signal_handler_options=SignalHandlerOptions.NO)
    stop = threading.Event()

    def on_signal(signum: int, frame: Any) -> None:
        stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)

    names = [name for name in SERVER_MODULES if name in report.servers]
    nodes = []
    for name in names:
        node_class = getattr(importlib.import_module(SERVER_MODULES[name]), _SERVER_CLASSES[name])
        node = node_class(args.params_file)
        if args.use_sim_time:
            # The servers only: the manager's bonds are on the steady clock, and /clock would wake it.
            node.set_parameters([Parameter("use_sim_time", Parameter.Type.BOOL, True)])
        nodes.append(node)
    executor = SingleThreadedExecutor()
    for node in nodes:
        executor.add_node(node)
    loop = ServerLoop(executor, [node.intake for node in nodes])
    manager = LifecycleManager(
        [InProcessServer(name) for name in names], bond_timeout=args.bond_timeout, namespace=namespace
    )
    if args.no_autostart:
        manager.target_state = "unconfigured"

    def wake() -> None:
        loop.wake()
        manager.wake()

    wake_on_signals(wake)
    outcome = {"code": 0}
    manager_thread = threading.Thread(
        target=_manage, args=(manager, names, stop, wake, args.ready_fd, outcome), name="lifecycle-manager"
    )
    manager_thread.start()
    try:
        loop.run(stop, nodes[0].get_logger())
    finally:
        stop.set()
        manager.wake()
        manager_thread.join()
        # Measurements stop first, destinations flush last, as dc-bringup stops server processes.
        for name, node in reversed(list(zip(names, nodes, strict=True))):
            if node.lifecycle_state in ("active", "inactive", "unconfigured"):
                node.trigger_shutdown()
                manager.get_logger().info(f"{name} stopped")
        executor.shutdown(timeout_sec=1.0)
        for node in nodes:
            node.destroy_node()
        manager.destroy_node()
        if rclpy.utilities.ok():
            rclpy.shutdown()
        sys.stdout.flush()
    return outcome["code"]


def _manage(
    manager: Any, names: list[str], stop: threading.Event, wake: Any, ready_fd: int, outcome: dict[str, int]
) -> None:
    """The manager's loop, on its thread: bring the servers up, then serve commands and watch heartbeats."""
    try:
        if not manager.start_all():
            outcome["code"] = 1
            return
        if manager.target_state == "unconfigured":
            manager.get_logger().info("DC is waiting for startup (dc lifecycle startup): " + ", ".join(names))
        else:
            manager.get_logger().info(f"DC is up in one process (pid {os.getpid()}): " + ", ".join(names))
        if ready_fd >= 0:
            with contextlib.suppress(OSError):
                os.write(ready_fd, READY)
                os.close(ready_fd)
        while not stop.is_set() and not manager.shutdown_requested:
            manager.wait_for_work()
            manager.run_commands()
            manager.check_bonds()
    except Exception as exc:  # the manager must not die silently while the servers run on
        manager.get_logger().fatal(f"lifecycle manager failed: {exc!r}")
        outcome["code"] = 1
    finally:
        stop.set()
        wake()


class _Interrupted(Exception):
    """Raised by the supervisor's signal handler to end a blocking wait."""


def supervise(args: argparse.Namespace, params_file: str, server_count: int) -> int:
    """dc-bringup --single-process: run the servers' process, restart it when it dies, stop it on a signal.

    A process that fails before it ever came up is not restarted (a configuration or start-up
    error would only repeat): its exit code is dc-bringup's. Once up, any exit but a requested
    stop or shutdown is a failure, restarted after a delay that doubles while failures repeat.
    """
    cmd = [sys.executable, "-m", "dc_bringup.single_process", params_file, "--log-level", args.log_level]
    cmd += ["--bond-timeout", str(args.bond_timeout)]
    if args.namespace.strip("/"):
        cmd += ["--namespace", args.namespace]
    if args.use_sim_time:
        cmd.append("--use-sim-time")
    if args.no_autostart:
        cmd.append("--no-autostart")
    stopping = threading.Event()
    interruptible = threading.Event()

    def on_signal(signum: int, frame: Any) -> None:
        stopping.set()
        if interruptible.is_set():
            raise _Interrupted()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    was_up = False
    delay = FIRST_RETRY_DELAY_S
    while True:
        read_end, write_end = os.pipe()
        started = time.monotonic()
        # Own process group: a terminal's Ctrl-C reaches dc-bringup only, which stops the servers in order.
        process = subprocess.Popen(
            [*cmd, "--ready-fd", str(write_end)], pass_fds=(write_end,), preexec_fn=die_with_parent, process_group=0
        )
        os.close(write_end)
        code = _wait(process, read_end, stopping, interruptible, args.stop_timeout * server_count)
        up = _read_ready(read_end)
        os.close(read_end)
        was_up = was_up or up
        if stopping.is_set() or code == 0 or not was_up:
            return code if code >= 0 else 1
        if time.monotonic() - started > HEALTHY_AFTER_S:
            delay = FIRST_RETRY_DELAY_S
        how = f"was killed by signal {-code}" if code < 0 else f"exited with code {code}"
        _say(f"the servers' process {how}: restarting it in {delay:g} s")
        try:
            interruptible.set()
            if stopping.is_set() or stopping.wait(delay):
                return 0
        except _Interrupted:
            return 0
        finally:
            interruptible.clear()
        delay = min(2 * delay, MAX_RETRY_DELAY_S)


def _wait(
    process: subprocess.Popen[bytes],
    ready: int,
    stopping: threading.Event,
    interruptible: threading.Event,
    stop_timeout: float,
) -> int:
    """The process' exit code; on a signal, stop it (SIGTERM, then SIGKILL after ``stop_timeout``)."""
    try:
        interruptible.set()
        if not stopping.is_set():
            return process.wait()
    except _Interrupted:
        pass
    finally:
        interruptible.clear()
    process.send_signal(signal.SIGTERM)
    try:
        return process.wait(stop_timeout)
    except subprocess.TimeoutExpired:
        _say(f"the servers' process did not stop in {stop_timeout:g} s: killing it")
        process.kill()
        return process.wait()


def _read_ready(read_end: int) -> bool:
    os.set_blocking(read_end, False)
    try:
        return os.read(read_end, len(READY)) == READY
    except BlockingIOError:
        return False


def _say(message: str) -> None:
    print(f"[dc-bringup] {message}", file=sys.stderr, flush=True)


if __name__ == "__main__":
    sys.exit(main())
