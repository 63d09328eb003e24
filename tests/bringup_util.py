"""Run `dc-bringup` in a subprocess and read what a user would see: records on stdout, logs on stderr."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any, ClassVar

from tests.domains import fresh_domain_id

REPO = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).parent


def server_env(home: Path, domain_id: int | None = None) -> dict[str, str]:
    """The environment of DC's servers started by a test: a ROS domain of their own (a fresh one unless
    given), discovery on this machine only, unbuffered output, and run id counters, buffers and data
    under ``home`` (created) as $HOME and $XDG_DATA_HOME, inside the test."""
    home.mkdir(parents=True, exist_ok=True)
    return dict(
        os.environ,
        ROS_DOMAIN_ID=str(fresh_domain_id() if domain_id is None else domain_id),
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
        PYTHONUNBUFFERED="1",
        HOME=str(home),
        XDG_DATA_HOME=str(home / ".local" / "share"),
    )


class Bringup:
    # Arguments every dc-bringup of a test gets: the bringup_mode fixture (conftest.py) sets
    # ["--single-process"] to run a test in both modes.
    mode_args: ClassVar[list[str]] = []

    def __init__(
        self,
        params: Path | str,
        home: Path,
        *,
        args: Sequence[str] = (),
        env: dict[str, str] | None = None,
        command: Sequence[str] = (),
    ) -> None:
        self.params = Path(params)
        self.args = [*self.mode_args, *args]
        # A whole command line instead of `dc-bringup PARAMS ARGS` (the one ros/dc_launch builds).
        self.command = list(command) or [str(BIN / "dc-bringup"), str(self.params), *self.args]
        self.domain_id = fresh_domain_id()
        self.home = home
        self.env = server_env(home, self.domain_id)
        self.env.update(env or {})
        self.stdout: list[str] = []
        self.stderr: list[str] = []
        self._stdout_times: list[float] = []
        self._changed = threading.Condition()
        self.process: subprocess.Popen[str] | None = None
        self.returncode: int | None = None

    # -- process -----------------------------------------------------------------------------
    def __enter__(self) -> Bringup:
        self.process = subprocess.Popen(
            self.command,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=self.env,
            cwd=self.home,
        )
        for stream, sink, times in (
            (self.process.stdout, self.stdout, self._stdout_times),
            (self.process.stderr, self.stderr, None),
        ):
            threading.Thread(target=self._read, args=(stream, sink, times), daemon=True).start()
        return self

    def _read(self, stream: Any, sink: list[str], times: list[float] | None) -> None:
        for line in stream:
            with self._changed:
                sink.append(line.rstrip("\n"))
                if times is not None:
                    times.append(time.monotonic())
                self._changed.notify_all()
        with self._changed:
            self._changed.notify_all()

    def stop(self, timeout: float = 30.0) -> int:
        assert self.process is not None
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGINT)
            try:
                self.process.wait(timeout)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self.returncode = self.process.returncode
        return self.returncode

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()

    def wait_exit(self, timeout: float) -> int:
        assert self.process is not None
        try:
            self.returncode = self.process.wait(timeout)
        except subprocess.TimeoutExpired:
            raise AssertionError(
                f"dc-bringup still running after {timeout} s\n--- stderr ---\n" + "\n".join(self.stderr[-80:])
            ) from None
        return self.returncode

    # -- reading -----------------------------------------------------------------------------
    def wait_until(self, check: Callable[[], bool], timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        with self._changed:
            while not check():
                left = deadline - time.monotonic()
                if left <= 0:
                    raise AssertionError(
                        f"timed out after {timeout} s waiting for {what}\n--- stdout ---\n"
                        + "\n".join(self.stdout[-50:])
                        + "\n--- stderr ---\n"
                        + "\n".join(self.stderr[-80:])
                    )
                self._changed.wait(min(left, 0.2))

    def wait_stderr(self, needle: str, timeout: float = 30.0) -> str:
        found: list[str] = []

        def check() -> bool:
            found[:] = [line for line in self.stderr if needle in line]
            return bool(found)

        self.wait_until(check, timeout, f"{needle!r} on stderr")
        return found[0]

    def records(self, predicate: Callable[[dict[str, Any]], bool] | None = None) -> list[dict[str, Any]]:
        out = []
        for line in list(self.stdout):
            try:
                value = json.loads(line)
            except json.JSONDecodeError:
                continue
            if isinstance(value, dict) and (predicate is None or predicate(value)):
                out.append(value)
        return out

    def named(self, name: str) -> list[dict[str, Any]]:
        """The records of one measurement (or group), oldest first by their date."""
        return sorted(self.records(lambda r: r.get("name") == name), key=lambda r: float(r["date"]))

    def record_times(self) -> list[float]:
        """Arrival time (monotonic) of each stdout line that is a JSON record."""
        return [t for line, t in zip(list(self.stdout), list(self._stdout_times), strict=False) if line.startswith("{")]

    def wait_records(
        self, n: int, timeout: float = 30.0, predicate: Callable[[dict[str, Any]], bool] | None = None
    ) -> list[dict[str, Any]]:
        self.wait_until(lambda: len(self.records(predicate)) >= n, timeout, f"{n} records on stdout")
        return self.records(predicate)

    def wait_ready(self, timeout: float = 120.0) -> None:
        # DC is up in ~10 s here; on a 2-core machine at load 15 (the suite's four workers and more) it
        # took over 60 s, and waiting costs nothing when it comes early.
        self.wait_stderr("DC is up", timeout)


# A line Fast DDS itself prints (coloured, dated, a RTPS_ category): e.g. "[RTPS_TRANSPORT_SHM Error] Failed
# init_port ...: open_and_lock_file failed" when a killed process left a shared-memory port locked. It is the
# middleware's, not DC's output: DC's processes send it to stderr, which a test reads without them.
FAST_DDS_LOG_LINE = re.compile(r"^(\x1b\[[0-9;]*m)?\d{4}-\d\d-\d\d \d\d:\d\d:\d\d\.\d+ .*RTPS_[A-Z_]+.*(\n|$)", re.M)


def dc(
    *args: str, env: dict[str, str] | None = None, timeout: float = 60.0, stdin: str | None = None
) -> subprocess.CompletedProcess[str]:
    """Run the `dc` command-line tool; its stderr without Fast DDS's own log lines (which DC's commands
    send there, never to stdout: dc_core.native_stdout)."""
    result = subprocess.run(
        [str(BIN / "dc"), *args], capture_output=True, text=True, env=env, timeout=timeout, input=stdin
    )
    result.stderr = FAST_DDS_LOG_LINE.sub("", result.stderr)
    return result


def example_1_with_robot_name_from(robot_file: Path, params: Path) -> Path:
    """The seed's example 1 whose records carry a robot_name read from ``robot_file`` at configure
    time: a server that cannot configure once the file is gone."""
    params.write_text(
        (REPO / "params" / "examples" / "example_1.yaml").read_text()
        + f"""
    custom_str_params_list: ["robot_name"]
    custom_str_params:
      robot_name:
        name: "robot_name"
        value_from_file: "{robot_file}"
"""
    )
    return params
