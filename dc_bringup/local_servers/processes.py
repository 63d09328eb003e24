"""What the local servers share about their processes: pids from files, stopping, log tails, free ports."""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import time
from pathlib import Path

LOG_TAIL_LINES = 20


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


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
