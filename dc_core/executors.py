"""Which rclpy executor drives a DC server, and the loop that spins it (experimental).

``single`` is rclpy's ``SingleThreadedExecutor``, the default of every server. ``events`` is
``rclpy.experimental.EventsExecutor``: its C++ event queue costs about an eighth of the CPU per
message (docs/performance.md) but it is experimental in Jazzy. In a probe its ``spin()`` never
fired timers, so servers drive it, like the default one, through :func:`spin_until` — a
``spin_once`` loop with a short timeout that also gives the main thread back to Python often
enough for a SIGTERM handler to stop the loop. tests/test_executors.py holds what is proven to
work under it: timers, subscriptions, lifecycle services (including subscriptions destroyed and
timers replaced from inside a transition) and SIGTERM shutdown of a real server process.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

from rclpy.context import Context
from rclpy.executors import Executor, ExternalShutdownException, SingleThreadedExecutor

EXECUTOR_KINDS = ("single", "events")
DEFAULT_EXECUTOR = "single"
SPIN_PERIOD_S = 0.1


def make_executor(kind: str = DEFAULT_EXECUTOR, *, context: Context | None = None) -> Executor:
    """A new executor of ``kind`` (one of :data:`EXECUTOR_KINDS`) for ``context`` (default context if None)."""
    if kind == "single":
        return SingleThreadedExecutor(context=context)
    if kind == "events":
        # Imported here: the experimental module enables faulthandler and loads C++ code that the
        # default executor never needs.
        from rclpy.experimental.events_executor import EventsExecutor

        return EventsExecutor(context=context)
    raise ValueError(f"unknown executor {kind!r}; expected one of {', '.join(EXECUTOR_KINDS)}")


def spin_until(
    executor: Executor,
    stop: threading.Event,
    on_error: Callable[[Exception], None],
    period: float = SPIN_PERIOD_S,
) -> None:
    """Run callbacks until ``stop`` is set or the context shuts down.

    A callback that raises is reported to ``on_error`` and the loop goes on: one bad record must
    not stop collection.
    """
    while not stop.is_set():
        try:
            executor.spin_once(timeout_sec=period)
        except (KeyboardInterrupt, ExternalShutdownException):
            return
        except Exception as exc:
            on_error(exc)
