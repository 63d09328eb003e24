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
import select
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from typing import Any

from dc_bringup.processes import die_with_parent
from dc_bringup.validate import SERVER_MODULES, check
from dc_core.native_stdout import original_stdout
from dc_core.ros_args import ROS_ARGS_END, ROS_ARGS_FLAG, namespace_remap, split_ros_args
from dc_core.signals import StopRequest

# The process asks its supervisor for a restart (EX_TEMPFAIL): a server stopped beating.
EXIT_RESTART = 75
# What the process writes on its status pipe to the supervisor: once when every server is up, then
# about every BEAT_PERIOD_S while its manager runs.
UP = b"u"
BEAT = b"."
BEAT_PERIOD_S = 1.0
# A process that fails is started again at once; if it keeps failing, after waits doubling from
# RETRY_DELAY_S up to MAX_RETRY_DELAY_S.
RETRY_DELAY_S = 1.0
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
        # Called before the restart of an unhealthy server (a thread of it died): only a new process
        # brings its threads back, and this one stops in order first, committing what it holds.
        raise ProcessRestart(self.name)


class ProcessRestart(Exception):
    """The manager asks for a restart of every server's process, after an orderly stop."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="dc_bringup.single_process")
    parser.add_argument("params_file")
    parser.add_argument("--log-level", default="info")
    parser.add_argument("--bond-timeout", type=float, default=10.0)
    parser.add_argument("--transition-timeout", type=float, default=None)
    parser.add_argument("--namespace", default="")
    parser.add_argument("--use-sim-time", action="store_true")
    parser.add_argument("--no-autostart", action="store_true")
    parser.add_argument("--restarted", action="store_true", help="not the first start: the warnings were printed")
    parser.add_argument("--status-fd", type=int, default=-1, help="pipe to the supervisor: up, then beats")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    own, ros_args = split_ros_args(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(own)
    namespace_arg = args.namespace if args.namespace.strip("/") else (namespace_remap(ros_args) or "")
    report, error = check(args.params_file, namespace_arg, ros_args)
    if report is None:
        print(f"dc-bringup: invalid configuration: {error}", file=sys.stderr)
        return 2
    if not args.restarted:
        for note in report.notes:
            print(f"dc-bringup: {note}", file=sys.stderr)
        for warning in report.warnings:
            print(f"dc-bringup: warning: {warning}", file=sys.stderr)

    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter

    from dc_bringup.manager import LifecycleManager, default_transition_timeout
    from dc_core.lifecycle import ServerLoop, init_server_process
    from dc_core.signals import wake_on_signals
    from dc_core.supervision import Supervisor
    from dc_core.topics import ros_namespace

    try:
        stop = init_server_process(args.log_level, args.namespace, ros_args)
    except Exception as exc:  # rclpy's RCLError, UnknownROSArgsError: both say which argument
        print(f"dc-bringup: invalid --ros-args: {exc}", file=sys.stderr)
        return 2
    joined = time.monotonic()  # graph discovery runs from the first node on: the manager's wait counts from here
    namespace = ros_namespace(namespace_arg) if namespace_arg.strip("/") else ""

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
        [InProcessServer(name) for name in names],
        bond_timeout=args.bond_timeout,
        namespace=namespace,
        discovery_from=joined,
        transition_timeout=args.transition_timeout or default_transition_timeout(report.configs),
    )
    if args.no_autostart:
        manager.target_state = "unconfigured"

    def wake() -> None:
        loop.wake()
        manager.wake()

    outcome = {"code": 0}
    # Without its signal relay the loop would not see a stop at once: the process is restarted, in order.
    relay_supervisor = Supervisor(manager.get_logger())

    def restart_process(reason: str) -> None:
        outcome["code"] = EXIT_RESTART
        stop.set()
        wake()

    relay_supervisor.add_listener(restart_process)
    wake_on_signals(wake, stop, relay_supervisor)
    manager_thread = threading.Thread(
        target=_manage, args=(manager, names, stop, wake, args.status_fd, outcome), name="lifecycle-manager"
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
    manager: Any, names: list[str], stop: StopRequest, wake: Any, status_fd: int, outcome: dict[str, int]
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
        status = _StatusPipe(status_fd)
        status.send(UP)
        while not stop.is_set() and not manager.shutdown_requested:
            manager.wait_for_work()
            manager.run_commands()
            manager.check_bonds()
            status.beat()
    except ProcessRestart as restart:
        manager.get_logger().error(
            f"{restart} must be restarted: stopping every server in order, then restarting their process"
        )
        outcome["code"] = EXIT_RESTART
    except Exception as exc:  # the manager must not die silently while the servers run on
        manager.supervisor.failed("lifecycle-manager", exc)  # logged with its traceback, counted
        outcome["code"] = 1
    finally:
        stop.set()
        wake()


class _StatusPipe:
    """The process' end of the supervisor's status pipe (none when run by hand)."""

    def __init__(self, fd: int) -> None:
        self._fd = fd
        self._last = time.monotonic()
        if fd >= 0:
            os.set_blocking(fd, False)  # a supervisor that stopped reading must not stop the manager

    def send(self, what: bytes) -> None:
        if self._fd >= 0:
            # A supervisor that is gone is no reason to stop collecting.
            with contextlib.suppress(OSError):
                os.write(self._fd, what)
            self._last = time.monotonic()

    def beat(self) -> None:
        # The manager turns at every heartbeat of every server: a beat a second is enough.
        if time.monotonic() - self._last >= BEAT_PERIOD_S:
            self.send(BEAT)


class _Interrupted(Exception):
    """Raised by the supervisor's signal handler to end a blocking wait."""


def supervise(args: argparse.Namespace, params_file: str) -> int:
    """dc-bringup --single-process: run the servers' process, restart it when it dies or freezes, stop it on a signal.

    A process that fails before it ever came up is not restarted (a configuration or start-up
    error would only repeat): its exit code is dc-bringup's. Once up, any exit but a requested
    stop or shutdown is a failure, and so is a process whose status pipe stays silent for
    ``--bond-timeout`` (stopped, or frozen so hard that its own manager cannot act): it is
    restarted, at once the first time, then after waits that double while failures repeat.
    """
    cmd = [sys.executable, "-m", "dc_bringup.single_process", params_file, "--log-level", args.log_level]
    cmd += ["--bond-timeout", str(args.bond_timeout)]
    if args.transition_timeout:
        cmd += ["--transition-timeout", str(args.transition_timeout)]
    if args.namespace.strip("/"):
        cmd += ["--namespace", args.namespace]
    if args.use_sim_time:
        cmd.append("--use-sim-time")
    if args.no_autostart:
        cmd.append("--no-autostart")
    if args.ros_args:
        cmd += [ROS_ARGS_FLAG, *args.ros_args, ROS_ARGS_END]
    # The handler sets a flag and, where the main thread waits for it, interrupts the wait: nothing
    # that takes a lock (dc_core.signals), so a burst of signals cannot hang it.
    stopping = StopRequest()
    interruptible = threading.Event()

    def on_signal(signum: int, frame: Any) -> None:
        stopping.on_signal(signum, frame)
        if interruptible.is_set():
            raise _Interrupted()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    was_up = False
    delay = 0.0
    while True:
        read_end, write_end = os.pipe()
        started = time.monotonic()
        # Own process group: a terminal's Ctrl-C reaches dc-bringup only, which stops the servers in order.
        process = subprocess.Popen(
            [*cmd, "--status-fd", str(write_end), *(["--restarted"] if was_up else [])],
            pass_fds=(write_end,),
            preexec_fn=die_with_parent,
            process_group=0,
            stdout=original_stdout(),  # the records, on dc-bringup's own standard output
        )
        os.close(write_end)
        try:
            code, up = _watch(process, read_end, stopping, interruptible, args.bond_timeout)
        finally:
            os.close(read_end)
        if stopping.is_set():
            # --stop-timeout is per server, and the file was not parsed here: allow for every kind.
            code = _stop(process, args.stop_timeout * len(SERVER_MODULES))
        was_up = was_up or up
        if stopping.is_set() or code == 0 or not was_up:
            return code if code >= 0 else 1
        if time.monotonic() - started > HEALTHY_AFTER_S:
            delay = 0.0
        how = f"was killed by signal {-code}" if code < 0 else f"exited with code {code}"
        _say(f"the servers' process {how}: restarting it" + (f" in {delay:g} s" if delay else ""))
        try:
            interruptible.set()
            if stopping.is_set() or stopping.wait(delay):
                return 0
        except _Interrupted:
            return 0
        finally:
            interruptible.clear()
        delay = min(max(2 * delay, RETRY_DELAY_S), MAX_RETRY_DELAY_S)


def _watch(
    process: subprocess.Popen[bytes],
    status: int,
    stopping: StopRequest,
    interruptible: threading.Event,
    bond_timeout: float,
) -> tuple[int, bool]:
    """Until the process exits, is killed for its silence, or a signal asks to stop: (exit code, came up).

    The process writes :data:`UP` on its status pipe once its servers are up, then :data:`BEAT`
    about every second; the pipe's end of file is its exit.
    """
    up = False
    last = time.monotonic()
    while True:
        try:
            interruptible.set()
            if stopping.is_set():
                return -1, up
            timeout = max(0.0, last + bond_timeout - time.monotonic()) if up else None
            readable, _, _ = select.select([status], [], [], timeout)
        except _Interrupted:
            return -1, up
        finally:
            interruptible.clear()
        if not readable:
            _say(f"the servers' process sent nothing for {bond_timeout:g} s (bond_timeout): killing it")
            process.kill()
            return process.wait(), up
        data = os.read(status, 64)
        if not data:
            return process.wait(), up
        up = up or UP in data
        last = time.monotonic()


def _stop(process: subprocess.Popen[bytes], timeout: float) -> int:
    """SIGTERM (the servers stop in order), then SIGKILL after ``timeout`` seconds."""
    if process.poll() is None:
        process.send_signal(signal.SIGTERM)
    try:
        return process.wait(timeout)
    except subprocess.TimeoutExpired:
        _say(f"the servers' process did not stop in {timeout:g} s: killing it")
        process.kill()
        return process.wait()


def _say(message: str) -> None:
    print(f"[dc-bringup] {message}", file=sys.stderr, flush=True)


if __name__ == "__main__":
    sys.exit(main())
