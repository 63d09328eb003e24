"""What every plugin is, whatever its kind: parameters, a context, lifecycle hooks, counters.

The three kinds (:class:`dc_core.measurement.Measurement`, :class:`dc_core.condition.Condition`,
:class:`dc_core.destination.Destination`) add only their own work to :class:`Plugin`. A plugin
names its parameters once, as the type argument of its base::

    class Battery(Measurement[BatteryParams]):
        ...

``self.params`` is then a ``BatteryParams`` for the type checker, and ``Battery.Params`` (the class
the server parses the YAML section with) is ``BatteryParams`` at run time. A plugin written before
this (``class Battery(Measurement): Params = BatteryParams``) works unchanged.
"""

from __future__ import annotations

import abc
import threading
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING, Any, ClassVar, Generic, Protocol, TypeVar, get_args, get_origin

from dc_core.errors import ConfigError, DcError, PluginError
from dc_core.logs import Logger
from dc_core.params import NoParams

if TYPE_CHECKING:
    from rclpy.qos import QoSProfile

    from dc_core.worker import Worker

ParamsT = TypeVar("ParamsT")

MessageCallback = Callable[[Any, Any], None]
"""Called with a message and its ``MessageInfo`` (a dict: source timestamp, publication sequence number)."""


class PluginContext(Protocol):
    """What a server gives each of its plugins: the same ways in for every kind."""

    @property
    def name(self) -> str:
        """The plugin instance's name in the YAML file."""

    @property
    def logger(self) -> Logger:
        """A logger named after the instance."""

    @property
    def node(self) -> Any:
        """The server's rclpy node (``None`` without ROS): for what the context does not offer."""

    def subscribe(
        self, msg_type: Any, topic: str, callback: MessageCallback, qos: QoSProfile, *, raw: bool = False
    ) -> Any:
        """Subscribe to any ROS message type; ``callback(message, message_info)`` on the main thread.

        ``raw``: ``message`` is the serialised message (bytes), not deserialised (no cost per field).

        The server takes these messages itself, outside rclpy's executor, which costs a fraction
        per message (docs/performance.md). Returns the subscription, for :meth:`unsubscribe`.
        """

    def unsubscribe(self, subscription: Any, *, take_queued: bool = False) -> None:
        """Destroy a subscription made by :meth:`subscribe`; with ``take_queued``, the messages the middleware
        already delivered to it go to its callback first (destroyed with it, they would be lost)."""

    def create_timer(self, period_s: float, callback: Callable[[], None]) -> Any:
        """Call ``callback()`` every ``period_s`` seconds on the main thread, until :meth:`destroy_timer`."""

    def destroy_timer(self, timer: Any) -> None:
        """Stop and release a timer made by :meth:`create_timer`."""

    @property
    def worker(self) -> Worker:
        """Threads for slow work: ``submit(job, on_done)`` runs ``job()`` on a thread and
        ``on_done(outcome)`` back on the main thread (dc_core.worker)."""

    def start_thread(self, target: Callable[[], Any], name: str) -> threading.Thread:
        """Start a daemon thread of the plugin's own under the server's supervision rule
        (dc_core.supervision): an exception that escapes ``target`` is logged with its traceback,
        counted, and makes the server unhealthy, so that it is restarted."""


class Plugin(abc.ABC, Generic[ParamsT]):
    """Base of the bases: see the module documentation.

    A plugin's one-line description is the first line of its class docstring (``dc list-plugins``,
    dc_core.plugins.describe).
    """

    Params: ClassVar[type] = NoParams

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if "Params" in cls.__dict__:
            return
        for base in getattr(cls, "__orig_bases__", ()):
            args = get_args(base)
            origin = get_origin(base)
            if args and isinstance(args[0], type) and isinstance(origin, type) and issubclass(origin, Plugin):
                cls.Params = NoParams if args[0] is type(None) else args[0]
                return

    def __init__(self, context: PluginContext, params: ParamsT) -> None:
        self.context = context
        self.params = params

    def on_configure(self) -> None:
        """Check and open what the plugin needs (files, subscriptions); raise
        :class:`dc_core.errors.PluginError` to fail configure with a clear message."""

    def on_activate(self) -> None:
        """Called when the server activates."""

    def on_deactivate(self) -> None:
        """Called when the server deactivates; flush and close what activation opened."""

    def on_cleanup(self) -> None:
        """Release what ``on_configure`` opened."""

    def counters(self) -> dict[str, int]:
        """Counters of the plugin's own (e.g. malformed input), served beside the server's for it."""
        return {}


def run_hook(what: str, plugin: Plugin[Any], hook: str) -> None:
    """``plugin.<hook>()``, a failure named after the plugin: ``PluginError("<what>: <hook> failed: ...")``.

    ``what`` says which instance ("destination flb_pg (dc_destinations/PgSQL)"). A ConfigError
    passes unchanged: it names its YAML path already.
    """
    try:
        getattr(plugin, hook)()
    except ConfigError:
        raise
    except Exception as exc:
        raise PluginError(f"{what}: {hook} failed: {exc}") from exc


def run_hook_on_each(plugins: Iterable[tuple[str, Plugin[Any]]], hook: str) -> list[str]:
    """``plugin.<hook>()`` on every plugin, even after one failed; returns one message per failure."""
    errors = []
    for what, plugin in plugins:
        try:
            run_hook(what, plugin, hook)
        except DcError as exc:
            errors.append(str(exc))
    return errors
