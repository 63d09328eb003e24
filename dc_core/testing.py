"""Test doubles for plugin authors (DC's own tests use them too): a logger and plugin contexts.

Test a plugin the way a server runs it, without starting one::

    from dc_core.params import parse_params
    from dc_core.testing import PluginHarness

    harness = PluginHarness()
    battery = harness.start(Battery, {"low_percent": 15.0})   # parsed, configured, activated
    assert battery.collect()["percentage"] <= 100
    harness.stop(battery)                                     # deactivated, cleaned up

With a ROS node (``PluginHarness(node)``), ``context.subscribe`` and ``context.create_timer`` are the
node's own subscriptions and timers, served by whatever executor spins that node; without one they
raise. Slow work that a plugin gives ``context.worker`` comes back when the test calls
``harness.run_finished_work()`` (a server does so from its loop).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, TypeVar

from dc_core.measurement import BasePaths
from dc_core.params import parse_params
from dc_core.plugin import MessageCallback, Plugin
from dc_core.supervision import Supervisor
from dc_core.worker import Worker

PluginT = TypeVar("PluginT", bound=Plugin[Any])


class RecordingLogger:
    """A :class:`dc_core.logs.Logger` that keeps ``(level, message)`` pairs and also logs them."""

    def __init__(self, name: str = "dc.test") -> None:
        self.lines: list[tuple[str, str]] = []
        self._log = logging.getLogger(name)

    def _add(self, level: str, message: str) -> None:
        self.lines.append((level, message))
        self._log.log(logging.getLevelName(level.upper()), message)

    def debug(self, message: str, /, **kwargs: Any) -> None:
        self._add("debug", message)

    def info(self, message: str, /, **kwargs: Any) -> None:
        self._add("info", message)

    def warning(self, message: str, /, **kwargs: Any) -> None:
        self._add("warning", message)

    def error(self, message: str, /, **kwargs: Any) -> None:
        self._add("error", message)

    def at(self, level: str) -> list[str]:
        """The messages logged at ``level``."""
        return [message for logged, message in self.lines if logged == level]


@dataclass
class Emitted:
    """A record a measurement emitted from an event."""

    record: dict[str, Any]
    stamp_ns: int | None
    group_key: str | None


@dataclass
class FakeContext:
    """A plugin context of any kind (dc_core.plugin.PluginContext, MeasurementContext) for tests."""

    name: str = "plugin"
    logger: RecordingLogger = field(default_factory=RecordingLogger)
    node: Any = None
    paths: BasePaths = field(default_factory=BasePaths)
    emitted: list[Emitted] = field(default_factory=list)
    worker_woken: threading.Event = field(default_factory=threading.Event)
    _worker: Worker | None = None
    _supervisor: Supervisor | None = None

    def subscribe(self, msg_type: Any, topic: str, callback: MessageCallback, qos: Any, *, raw: bool = False) -> Any:
        node = self._require_node("subscribe")
        # rclpy hands a callback of two parameters the message and its MessageInfo, as the intake does.
        return node.create_subscription(msg_type, topic, lambda msg, info: callback(msg, info), qos, raw=raw)

    def unsubscribe(self, subscription: Any, *, take_queued: bool = False) -> None:
        node = self._require_node("unsubscribe")
        while take_queued:
            with subscription.handle:
                taken = subscription.handle.take_message(subscription.msg_type, subscription.raw)
            if taken is None:
                break
            subscription.callback(*taken)
        node.destroy_subscription(subscription)

    def create_timer(self, period_s: float, callback: Callable[[], None]) -> Any:
        return self._require_node("create_timer").create_timer(period_s, callback)

    def destroy_timer(self, timer: Any) -> None:
        timer.cancel()
        self._require_node("destroy_timer").destroy_timer(timer)

    @property
    def worker(self) -> Worker:
        if self._worker is None:
            self._worker = Worker(f"{self.name}-worker", self.worker_woken.set, threads=2)
        return self._worker

    def start_thread(self, target: Callable[[], Any], name: str) -> threading.Thread:
        """A thread under a supervisor of this context's own: a failure is in ``logger``, ``supervisor`` counts it."""
        return self.supervisor.start_thread(target, name=name)

    @property
    def supervisor(self) -> Supervisor:
        if self._supervisor is None:
            self._supervisor = Supervisor(self.logger)
        return self._supervisor

    def stop_worker(self) -> None:
        """Stop the worker threads, if the plugin used them."""
        if self._worker is not None:
            self._worker.shutdown()
            self._worker = None

    def emit(self, record: dict[str, Any], *, stamp_ns: int | None = None, group_key: str | None = None) -> None:
        self.emitted.append(Emitted(record, stamp_ns, group_key))

    def _require_node(self, what: str) -> Any:
        if self.node is None:
            raise RuntimeError(f"{what} needs a ROS node: FakeContext(node=...) or PluginHarness(node)")
        return self.node


class PluginHarness:
    """Drives plugins through the lifecycle a server gives them, each with its own :class:`FakeContext`."""

    def __init__(self, node: Any = None) -> None:
        self.node = node
        self.contexts: dict[int, FakeContext] = {}

    def make(self, cls: type[PluginT], params: Mapping[str, Any] | None = None, name: str = "plugin") -> PluginT:
        """An instance with its parameters parsed from ``params`` (as its YAML section would give them)."""
        context = FakeContext(name=name, node=self.node)
        plugin = cls(context, parse_params(cls.Params, dict(params or {}), f"test.{name}"))
        self.contexts[id(plugin)] = context
        return plugin

    def start(self, cls: type[PluginT], params: Mapping[str, Any] | None = None, name: str = "plugin") -> PluginT:
        """Made, configured and activated."""
        plugin = self.make(cls, params, name)
        plugin.on_configure()
        plugin.on_activate()
        return plugin

    def context(self, plugin: Plugin[Any]) -> FakeContext:
        return self.contexts[id(plugin)]

    def run_finished_work(self, plugin: Plugin[Any], timeout: float = 10.0) -> int:
        """Wait for the plugin's worker jobs, then run their ``on_done`` here; returns how many ran."""
        worker = self.context(plugin).worker
        if not worker.wait_idle(timeout):
            raise TimeoutError(f"worker jobs of {self.context(plugin).name} still ran after {timeout} s")
        return worker.run_finished()

    def stop(self, plugin: Plugin[Any]) -> None:
        """Deactivated and cleaned up; its worker stopped."""
        plugin.on_deactivate()
        plugin.on_cleanup()
        self.contexts.pop(id(plugin)).stop_worker()
