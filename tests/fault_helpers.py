"""What the fault tests share: the fault hook's environment and a small real file system to fill.

Used by tests/test_e2e_never_silent.py and tests/test_fault_matrix.py.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

HOOKS = Path(__file__).resolve().parent / "fault_hooks"


def fault_env(tmp_path: Path, target: str, hang_s: float = 0.0, skip: int = 0, only_in: str = "") -> dict[str, str]:
    """The environment of a `dc-bringup` whose processes make ``target`` (``module:Class.method``)
    raise once, or with ``hang_s`` block that long once, after ``skip`` calls in each process ran
    normally, in the process of server module ``only_in`` alone when given
    (tests/fault_hooks/sitecustomize.py); the marker file says it did."""
    return {
        "PYTHONPATH": os.pathsep.join([*filter(None, [os.environ.get("PYTHONPATH")]), str(HOOKS)]),
        "DC_TEST_FAULT": target,
        "DC_TEST_FAULT_ONCE": str(tmp_path / "fault-raised"),
        **({"DC_TEST_FAULT_HANG": str(hang_s)} if hang_s else {}),
        **({"DC_TEST_FAULT_SKIP": str(skip)} if skip else {}),
        **({"DC_TEST_FAULT_IN": only_in} if only_in else {}),
    }


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
