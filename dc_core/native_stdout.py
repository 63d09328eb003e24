"""Standard output for Python alone: native code's lines go to standard error.

Fast DDS writes its own log lines (a killed peer's locked shared-memory port, a profile file it
cannot parse) from C++ straight to file descriptor 1. In DC that is where records go (the Stdout
destination, ``dc tap``) and where scripts read ``dc pub``'s and ``dc lifecycle``'s answers, so
``dc-bringup params.yaml | jq`` would read a middleware error as a record. After
:func:`python_only_stdout`, descriptor 1 is the process's standard error, for native code and for
child processes that inherit it, and Python's ``sys.stdout`` writes to the original output. A child
that must write there (dc-bringup's servers) is given :func:`original_stdout` explicitly.
"""

from __future__ import annotations

import os
import sys

_original: int | None = None


def python_only_stdout() -> None:
    """Move native code's standard output to standard error (once per process; before rclpy starts)."""
    global _original
    stdout = sys.stdout
    if _original is not None or stdout is None:
        return
    try:
        if stdout.fileno() != 1:
            return  # already somewhere else (a test's capture, a caller's own stream): not ours to move
        stdout.flush()
        original = os.dup(1)
        os.dup2(2, 1)
    except (OSError, ValueError, AttributeError):  # no descriptor 1 or 2, or a stdout without one
        return
    _original = original
    # Same encoding, errors and buffering as before: a terminal stays line-buffered, a pipe block-buffered.
    sys.stdout = open(  # noqa: SIM115 - the process's standard output, open until it exits
        original,
        "w",
        buffering=1 if stdout.line_buffering else -1,
        encoding=stdout.encoding,
        errors=stdout.errors,
        closefd=False,
    )


def original_stdout() -> int | None:
    """The descriptor of the process's own standard output, for a child that writes its output there
    (None where :func:`python_only_stdout` has not moved it: the child inherits descriptor 1)."""
    return _original
