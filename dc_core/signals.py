"""Signals that stop a process and wake its sleeping loop at once, with handlers safe to re-enter.

A server's main thread sleeps inside rcl's wait (C code) until something needs it. Python runs a
signal handler only when that thread comes back to the interpreter, so a SIGTERM would wait for the
next wake-up. ``signal.set_wakeup_fd`` makes the interpreter's C-level handler write a byte to a
socket at once; a thread reading it calls ``wake`` (a guard condition's trigger), the wait returns,
and the loop looks at its stop request.

A Python handler runs between two bytecodes of the main thread, possibly inside code that holds a
lock, and a second signal can interrupt the first handler. ``threading.Event.set`` takes a lock: a
burst of SIGTERMs hung a server on it (issue 33). :class:`StopRequest`'s handler therefore only
sets a flag and writes a byte to the wake-up socket (neither takes a lock); the relay thread, an
ordinary thread, turns the flag into the event that waiting threads see.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import socket
import threading
from collections.abc import Callable, Iterable
from typing import Any, Protocol

from dc_core.supervision import Supervisor


class StopFlag(Protocol):
    """What a loop asks of its stop request (a :class:`StopRequest`, or a ``threading.Event`` in tests)."""

    def is_set(self) -> bool: ...


class StopRequest(threading.Event):
    """A stop asked by a signal (:meth:`on_signal`) or by code (:meth:`set`); see the module documentation.

    An ``Event`` whose flag a signal handler may set: code written for an event takes it unchanged.
    """

    def __init__(self) -> None:
        super().__init__()
        self._requested = False
        self._wake_fd: int | None = None
        self.signals = 0  # how many stop signals came: a plain counter, safe in a handler

    def on_signal(self, signum: int, frame: Any) -> None:
        """The signal handler: a flag, a counter and a byte to the wake-up socket, nothing that locks."""
        self._requested = True
        self.signals += 1
        fd = self._wake_fd
        if fd is not None:
            # Non-blocking: a full socket already holds a wake-up that has not been read yet.
            with contextlib.suppress(OSError):
                os.write(fd, b"s")

    def install(self, signums: Iterable[int] = (signal.SIGINT, signal.SIGTERM)) -> None:
        """Make :meth:`on_signal` the handler of ``signums`` (main thread only)."""
        for signum in signums:
            signal.signal(signum, self.on_signal)

    def set(self) -> None:
        """Ask for the stop from code (never from a signal handler: this takes a lock)."""
        self._requested = True
        super().set()

    def is_set(self) -> bool:
        return self._requested or super().is_set()

    def clear(self) -> None:
        self._requested = False
        super().clear()

    def wait(self, timeout: float | None = None) -> bool:
        """Wait until the stop is asked (a signal's is seen once the relay thread read its wake-up)."""
        return super().wait(timeout) or self._requested

    def _relayed(self) -> None:
        """On the relay thread: a signal's flag becomes the event (ordinary code may take a lock)."""
        if self._requested and not super().is_set():
            super().set()


def stop_on_signals(signums: Iterable[int] = (signal.SIGINT, signal.SIGTERM)) -> StopRequest:
    """A :class:`StopRequest` that ``signums`` ask, and whose waiters they wake (for a process
    without a ROS loop to wake: a command-line tool; main thread only)."""
    stop = StopRequest()
    stop.install(signums)
    wake_on_signals(_nothing, stop)
    return stop


def _nothing() -> None:
    """No loop to wake: the relay only turns a signal's flag into the stop's event."""


def wake_on_signals(
    wake: Callable[[], None], stop: StopRequest | None = None, supervisor: Supervisor | None = None
) -> None:
    """Call ``wake`` on a thread of its own each time a signal with a Python handler arrives (main thread only).

    With ``stop``, its handler writes to the same socket after setting its flag, and threads
    waiting in ``stop.wait`` are woken once it is set. The thread runs under ``supervisor``'s rule
    (dc_core.supervision): without it, signals would no longer wake the loop.
    """
    reader, writer = socket.socketpair()
    writer.setblocking(False)  # a full buffer must never block the C handler: a lost byte is one lost wake-up
    signal.set_wakeup_fd(writer.fileno(), warn_on_full_buffer=False)
    if stop is not None:
        stop._wake_fd = writer.fileno()

    def relay() -> None:
        # The sockets live as long as the process: the thread is a daemon that dies with it.
        keep = (reader, writer)
        while keep[0].recv(64):
            if stop is not None:
                stop._relayed()
            wake()

    if supervisor is None:
        supervisor = Supervisor(logging.getLogger("dc.signals"))
    supervisor.start_thread(relay, name="signal-wakeup")
