"""Slow work off a server's main loop: run it on threads, get the outcome back on the main thread.

A server's main thread takes records, runs the timers of every measurement and sends the
heartbeat. A collection that waits on the network, a subprocess or a disk (a ping, ffmpeg, an image
written as JPEG, a map saved, a file hashed) would hold all of those up for as long as it takes.
:class:`Worker` runs such a function on one of its threads; its ``on_done`` callback runs later on
the main thread, when the server's loop drains finished work, so plugin state that the main thread
owns is never touched from two threads at once.

The server wakes its loop with ``wake`` (an rclpy guard condition's ``trigger``) whenever a job
finishes; :meth:`Worker.run_finished` is what the loop then calls.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

from dc_core.supervision import Supervisor

T = TypeVar("T")


@dataclass(frozen=True)
class Outcome(Generic[T]):
    """What a job gave: its ``value``, or the ``error`` it raised."""

    value: T | None = None
    error: BaseException | None = None

    def get(self) -> T:
        """The value, or the job's exception raised again."""
        if self.error is not None:
            raise self.error
        return self.value  # type: ignore[return-value]


class Worker:
    """Threads for slow jobs of one server; see the module documentation."""

    def __init__(
        self, name: str, wake: Callable[[], None], threads: int = 4, supervisor: Supervisor | None = None
    ) -> None:
        self._name = name
        self._pool = ThreadPoolExecutor(max_workers=threads, thread_name_prefix=name)
        self._wake = wake
        # A job's exception is its outcome; what fails around it (handing the outcome over, waking
        # the loop) would be lost in the pool's thread: it falls under the supervision rule.
        self._supervisor = supervisor if supervisor is not None else Supervisor(logging.getLogger(name))
        self._finished: queue.SimpleQueue[tuple[Callable[[Outcome[Any]], None], Outcome[Any]]] = queue.SimpleQueue()
        self._lock = threading.Lock()
        self._running = 0
        self._idle = threading.Condition(self._lock)

    def submit(self, job: Callable[[], T], on_done: Callable[[Outcome[T]], None]) -> None:
        """Run ``job()`` on a worker thread; ``on_done(outcome)`` then runs on the main thread."""
        with self._lock:
            self._running += 1
        future = self._pool.submit(job)
        future.add_done_callback(lambda f: self._finish(f, on_done))

    def _finish(self, future: Future[Any], on_done: Callable[[Outcome[Any]], None]) -> None:
        """On the job's thread, once it ended: its outcome handed over, the loop woken."""
        with self._supervisor.guard(f"{self._name} (handing over a finished job)"):
            try:
                self._hand_over(future, on_done)
            finally:
                with self._lock:
                    self._running -= 1
                    self._idle.notify_all()
            self._wake()

    def _hand_over(self, future: Future[Any], on_done: Callable[[Outcome[Any]], None]) -> None:
        if future.cancelled():  # cancelled by shutdown: its outcome is dropped, as documented
            return
        error = future.exception()
        outcome: Outcome[Any] = Outcome(error=error) if error is not None else Outcome(value=future.result())
        self._finished.put((on_done, outcome))

    def run_finished(self) -> int:
        """On the main thread: call ``on_done`` of every finished job; returns how many ran.

        A callback that raises does not keep the others from running; the first error is raised
        once all have run (the server's loop logs it).
        """
        ran = 0
        first_error: BaseException | None = None
        while True:
            try:
                on_done, outcome = self._finished.get_nowait()
            except queue.Empty:
                break
            ran += 1
            try:
                on_done(outcome)
            except Exception as exc:
                first_error = first_error or exc
        if first_error is not None:
            raise first_error
        return ran

    @property
    def running(self) -> int:
        """Jobs submitted and not finished yet."""
        with self._lock:
            return self._running

    def wait_idle(self, timeout: float) -> bool:
        """Wait until no job runs; False when some still do after ``timeout`` seconds."""
        with self._lock:
            return self._idle.wait_for(lambda: self._running == 0, timeout)

    def discard_finished(self) -> None:
        """Forget the outcomes not handed over yet (their callbacks never run)."""
        while True:
            try:
                self._finished.get_nowait()
            except queue.Empty:
                return

    def shutdown(self) -> None:
        """Stop taking jobs; jobs already running finish on their own, their outcomes are dropped."""
        self._pool.shutdown(wait=False, cancel_futures=True)
        self.discard_finished()
