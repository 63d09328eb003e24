"""One rule for every thread DC starts: an unexpected exception is logged, counted, and makes the server unhealthy.

A thread that dies takes its work with it: a dead writer left records in memory, a dead sender left
a destination's queue unsent, while the server went on saying it was fine. Every thread DC starts
runs through :meth:`Supervisor.start_thread` (or, for code run on threads DC does not own, such as a
thread pool's callbacks, inside :meth:`Supervisor.guard`): an exception that escapes it is

- logged once at error level with its traceback, naming the thread;
- counted in ``thread_failures`` (the server's metrics JSON, Prometheus text and `dc status`);
- remembered as the server's unhealthy reason: the health endpoint answers 503 and the heartbeat
  says so (dc_core.lifecycle), and the lifecycle manager restarts the server, stopping it in order
  first so that what it holds in memory is committed (docs/delivery.md, "What a stop can lose").

A thread that ends by returning is not a failure. The supervisor never restarts a thread itself: a
thread's state after an unexpected exception is unknown, and a restart of the server is the one
way back to a known state that DC has tested.
"""

from __future__ import annotations

import threading
import traceback
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

from dc_core.logs import Logger


class Supervisor:
    """The thread failures of one server (or of a component used alone, as in tests); see the module documentation."""

    def __init__(self, logger: Logger) -> None:
        self.logger = logger
        self._lock = threading.Lock()
        self.thread_failures = 0
        # The first failure's "thread NAME: ExcType: message": why the server is unhealthy.
        self.unhealthy_reason: str | None = None
        self._listeners: list[Callable[[str], None]] = []

    @property
    def unhealthy(self) -> bool:
        return self.unhealthy_reason is not None

    def add_listener(self, listener: Callable[[str], None]) -> None:
        """Call ``listener(reason)`` after each failure was logged and counted (on the failing thread)."""
        self._listeners.append(listener)

    def start_thread(
        self,
        target: Callable[[], Any],
        name: str,
        *,
        daemon: bool = True,
        on_failure: Callable[[BaseException], None] | None = None,
    ) -> threading.Thread:
        """Start ``target`` on a thread named ``name`` under the rule; ``on_failure(exc)`` runs before the
        failure is counted and reported (to save what the thread held)."""

        def run() -> None:
            with self.guard(name, on_failure=on_failure):
                target()

        thread = threading.Thread(target=run, name=name, daemon=daemon)
        thread.start()
        return thread

    @contextmanager
    def guard(self, name: str, *, on_failure: Callable[[BaseException], None] | None = None) -> Iterator[None]:
        """Run the ``with`` body under the rule; the exception does not propagate (the thread ends)."""
        try:
            yield
        except BaseException as exc:  # whatever it is, the thread is gone: never silently
            if isinstance(exc, SystemExit) and not exc.code:
                return  # a thread that asked to end is not a failure
            # What the thread held is put back first: whoever sees the server unhealthy sees it waiting.
            if on_failure is not None:
                try:
                    on_failure(exc)
                except Exception as again:
                    self.logger.error(f"thread {name}: saving its work after the failure failed too: {again!r}")
            self.failed(name, exc)

    def failed(self, name: str, exc: BaseException) -> None:
        """Log, count and remember a failure of thread ``name`` (what :meth:`guard` does with an exception)."""
        reason = f"thread {name}: {type(exc).__name__}: {exc}"
        trace = "".join(traceback.format_exception(exc))
        with self._lock:
            self.thread_failures += 1
            count = self.thread_failures
            if self.unhealthy_reason is None:
                self.unhealthy_reason = reason
        # Counted before it is logged: whoever reads the line finds the counter saying it too.
        self.logger.error(
            f"{reason} — the thread died (thread_failures {count}); the server is unhealthy and will be "
            f"restarted\n{trace}"
        )
        for listener in list(self._listeners):
            try:
                listener(reason)
            except Exception as again:
                self.logger.error(f"thread failure listener failed: {again!r}")

    def metrics(self) -> dict[str, Any]:
        """What the server's metrics JSON shows under ``threads``."""
        return {"thread_failures": self.thread_failures, "unhealthy": self.unhealthy_reason or ""}

    def prometheus(self) -> str:
        """The counter in Prometheus text (format 0.0.4), to append to a server's own."""
        return (
            "# HELP dc_thread_failures_total Threads of this server that died by an unexpected exception\n"
            "# TYPE dc_thread_failures_total counter\n"
            f"dc_thread_failures_total {self.thread_failures}\n"
        )
