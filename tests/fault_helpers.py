"""What the fault tests share: the fault hook's environment and a small real file system to fill.

Used by the tests of faults and of a full disk (tests/test_e2e_never_silent.py, test_fault_matrix.py,
test_delivery.py, test_supervision.py, test_logging_clash.py).
"""

from __future__ import annotations

import contextlib
import errno
import os
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

HOOKS = Path(__file__).resolve().parent / "fault_hooks"


def fault_env(
    tmp_path: Path, target: str, hang_s: float = 0.0, skip: int = 0, only_in: str = "", gate: Path | None = None
) -> dict[str, str]:
    """The environment of a `dc-bringup` whose processes make ``target`` (``module:Class.method``)
    raise once, or with ``hang_s`` block that long once, after ``skip`` calls in each process ran
    normally, in the process of server module ``only_in`` alone when given
    (tests/fault_hooks/sitecustomize.py); the marker file says it did. With ``gate`` (a FIFO from
    :func:`fault_gate`), the faulting call waits until :meth:`FaultGate.open` is called."""
    return {
        **({"DC_TEST_FAULT_GATE": str(gate)} if gate else {}),
        "PYTHONPATH": os.pathsep.join([*filter(None, [os.environ.get("PYTHONPATH")]), str(HOOKS)]),
        "DC_TEST_FAULT": target,
        "DC_TEST_FAULT_ONCE": str(tmp_path / "fault-raised"),
        **({"DC_TEST_FAULT_HANG": str(hang_s)} if hang_s else {}),
        **({"DC_TEST_FAULT_SKIP": str(skip)} if skip else {}),
        **({"DC_TEST_FAULT_IN": only_in} if only_in else {}),
    }


@contextlib.contextmanager
def fault_gate(tmp_path: Path) -> Iterator[FaultGate]:
    """A FIFO for ``fault_env(gate=...)``: the fault waits on it until the test opens the gate."""
    gate = FaultGate(tmp_path / "fault-gate")
    try:
        yield gate
    finally:
        gate.close()


class FaultGate:
    def __init__(self, path: Path) -> None:
        self.path = path
        os.mkfifo(path)
        # Read-write, so that neither side's open blocks and the byte stays in the pipe until read.
        self._fd: int | None = os.open(path, os.O_RDWR | os.O_NONBLOCK)

    def open(self) -> None:
        """Let the fault happen."""
        assert self._fd is not None
        os.write(self._fd, b"!")

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


@contextlib.contextmanager
def tmpfs(mount_point: Path, size: str = "4m") -> Iterator[Path]:
    """A real file system of ``size`` (tmpfs) at ``mount_point``, so that the buffer meets a real
    ENOSPC; the test is skipped where mounting needs a root this run does not have."""
    mount_point.mkdir(parents=True, exist_ok=True)
    mounted = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(mount_point)], capture_output=True, text=True
    )
    if mounted.returncode != 0:
        pytest.skip(f"mounting a small tmpfs needs root: {mounted.stderr.strip()}")
    try:
        yield mount_point
    finally:
        subprocess.run(["umount", "--lazy", str(mount_point)], check=False)


def fill(path: Path) -> None:
    """Write zeros into ``path`` until its file system has no space left.

    Unbuffered: a buffered file would keep the bytes of the write that met ENOSPC and raise again
    when closed."""
    descriptor = os.open(path, os.O_WRONLY | os.O_CREAT)
    try:
        while True:
            os.write(descriptor, b"\0" * 65536)
    except OSError as exc:
        assert exc.errno == errno.ENOSPC, exc
    finally:
        os.close(descriptor)
