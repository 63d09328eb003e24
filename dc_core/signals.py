"""Signals that wake a sleeping loop at once.

A server's main thread sleeps inside rcl's wait (C code) until something needs it. Python runs a
signal handler only when that thread comes back to the interpreter, so a SIGTERM would wait for the
next wake-up. ``signal.set_wakeup_fd`` makes the interpreter's C-level handler write a byte to a
socket at once; a thread reading it calls ``wake`` (a guard condition's trigger), the wait returns,
and the handler (``stop.set()``) runs before the loop looks at its stop event.
"""

from __future__ import annotations

import signal
import socket
import threading
from collections.abc import Callable


def wake_on_signals(wake: Callable[[], None]) -> None:
    """Call ``wake`` on a thread of its own each time a signal with a Python handler arrives (main thread only)."""
    reader, writer = socket.socketpair()
    writer.setblocking(False)  # a full buffer must never block the C handler: a lost byte is one lost wake-up
    signal.set_wakeup_fd(writer.fileno(), warn_on_full_buffer=False)

    def relay() -> None:
        # The sockets live as long as the process: the thread is a daemon that dies with it.
        keep = (reader, writer)
        while keep[0].recv(64):
            wake()

    threading.Thread(target=relay, name="signal-wakeup", daemon=True).start()
