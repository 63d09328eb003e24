"""Server processes started by dc-bringup: one per server, dying with the launcher."""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import subprocess
import sys
from collections.abc import Sequence
from typing import Protocol

from dc_core.native_stdout import original_stdout
from dc_core.ros_args import ROS_ARGS_END, ROS_ARGS_FLAG

_PR_SET_PDEATHSIG = 1


class ManagedServerHandle(Protocol):
    """What the lifecycle manager needs of a server it starts, watches and restarts."""

    name: str

    @property
    def pid(self) -> int | None: ...

    def start(self) -> None: ...

    def running(self) -> bool: ...

    def exit_code(self) -> int | None: ...

    def kill(self) -> None: ...

    def stop(self, timeout: float) -> int | None: ...


def die_with_parent() -> None:
    """SIGTERM to this process when its parent exits: a server when dc-bringup is killed with -9, and
    dc-bringup itself when its launcher is (--stop-with-parent); neither must live on as an orphan."""
    with contextlib.suppress(OSError):
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)


class ServerProcess:
    def __init__(
        self,
        name: str,
        module: str,
        params_file: str,
        log_level: str,
        namespace: str = "",
        use_sim_time: bool = False,
        ros_args: Sequence[str] = (),
    ) -> None:
        self.name = name
        self.module = module
        self.params_file = params_file
        self.log_level = log_level
        self.namespace = namespace
        self.use_sim_time = use_sim_time
        self.ros_args = list(ros_args)
        self.process: subprocess.Popen[bytes] | None = None
        self.starts = 0

    def start(self) -> None:
        cmd = [sys.executable, "-m", self.module, self.params_file, "--log-level", self.log_level]
        if self.namespace:
            cmd += ["--namespace", self.namespace]
        if self.use_sim_time:
            cmd.append("--use-sim-time")
        if self.ros_args:
            cmd += [ROS_ARGS_FLAG, *self.ros_args, ROS_ARGS_END]
        # Own process group: a terminal's Ctrl-C reaches dc-bringup only, which stops servers in order.
        # Its records on dc-bringup's own standard output, whatever native code of this process writes.
        self.process = subprocess.Popen(
            cmd, preexec_fn=die_with_parent, process_group=0, env=os.environ.copy(), stdout=original_stdout()
        )
        self.starts += 1

    @property
    def pid(self) -> int | None:
        return self.process.pid if self.process is not None else None

    def running(self) -> bool:
        return self.process is not None and self.process.poll() is None

    def exit_code(self) -> int | None:
        return None if self.process is None else self.process.poll()

    def stop(self, timeout: float) -> int | None:
        """SIGTERM, then SIGKILL after ``timeout`` seconds."""
        if self.process is None:
            return None
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(timeout)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        return self.process.returncode

    def kill(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.kill()
            self.process.wait()
