"""What the local servers share about their processes: pids from files, stopping, log tails, ports."""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import time
from pathlib import Path

LOG_TAIL_LINES = 20


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def port_free(port: int) -> bool:
    """Whether ``port`` can be bound on loopback now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def port_of_last_start(state_dir: Path, port: int) -> int:
    """``port``; with 0, the port the server in ``state_dir`` had at its last start (the settings written
    for it stay valid), else a free one."""
    port_file = state_dir / "port"
    if port == 0 and port_file.is_file():
        port = int(port_file.read_text().strip() or 0)
    return port or free_port()


def remember_port(state_dir: Path, port: int) -> None:
    """Write what :func:`port_of_last_start` reads at the next start."""
    (state_dir / "port").write_text(f"{port}\n")


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    # A zombie (a killed child of this process not yet reaped) counts as gone.
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return True
    return state != "Z"


def wait_gone(pid: int, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while alive(pid) and time.monotonic() < deadline:
        time.sleep(0.05)


def kill(pid: int) -> None:
    """SIGKILL, and wait (5 s at most) for the process to be gone."""
    if alive(pid):
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
        wait_gone(pid, 5.0)


def terminate(pid: int, timeout: float) -> None:
    """SIGTERM, then SIGKILL when the process is still there after ``timeout`` s."""
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, signal.SIGTERM)
    wait_gone(pid, timeout)
    kill(pid)


def stop_server(pid_file: Path, process: subprocess.Popen[bytes] | None, timeout: float) -> None:
    """Stop the server whose pid ``pid_file`` holds (see :func:`terminate`) and forget the file.

    ``process``: the Popen of this Python process that started it, if it did; it is reaped so that
    no zombie is left behind (a server started by another `dc servers` run has none here).
    """
    pid = pid_from_file(pid_file)
    if pid is None:
        return
    terminate(pid, timeout)
    if process is not None:
        with contextlib.suppress(subprocess.TimeoutExpired):
            process.wait(1.0)
    pid_file.unlink(missing_ok=True)


def pid_from_file(path: Path) -> int | None:
    """The pid on the first line of ``path`` when that process is alive."""
    try:
        pid = int(path.read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return None
    return pid if alive(pid) else None


def log_tail(log_file: Path) -> str:
    """The last lines of a server's log, for an error message ("" when there is none)."""
    try:
        lines = log_file.read_text(errors="replace").splitlines()[-LOG_TAIL_LINES:]
    except OSError:
        return ""
    return ("\n--- end of " + str(log_file) + " ---\n" + "\n".join(lines)) if lines else ""
