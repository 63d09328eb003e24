"""The measurement plugin contract.

A measurement is one small class: its parameters (a frozen dataclass in ``Params``), its JSON
schema (``schema_file`` in ``<schema_package>/schemas/``) and ``collect()``. Everything common —
timer, gating, validation, metadata, publishing — is done by the measurement server.

Timer-driven measurements return a record from :meth:`Measurement.collect` (or ``None`` when they
have nothing). Event-driven ones set ``timer_driven`` to false and call ``context.emit(record)``
from their subscription callbacks.
"""

from __future__ import annotations

import abc
import json
from collections.abc import Callable
from dataclasses import dataclass, field
from importlib import resources
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

from dc_core.errors import PluginError
from dc_core.logs import Logger
from dc_core.params import NoParams
from dc_core.worker import Worker

if TYPE_CHECKING:
    from rclpy.qos import QoSProfile


@dataclass(frozen=True)
class BasePaths:
    """Expanded base paths of the measurement server, for plugins that save files."""

    save_local_base_path: str = ""
    all_base_path: str = ""
    remote_prefixes: dict[str, str] = field(default_factory=dict)


class MeasurementContext(Protocol):
    """What the server gives a measurement plugin."""

    @property
    def name(self) -> str: ...
    @property
    def logger(self) -> Logger: ...
    @property
    def node(self) -> Any:
        """The rclpy node, to create subscriptions in ``on_configure`` (``None`` without ROS)."""

    @property
    def paths(self) -> BasePaths: ...
    def emit(self, record: dict[str, Any], *, stamp_ns: int | None = None, group_key: str | None = None) -> None:
        """Offer a record from an event (gated, validated and published like a collected one)."""

    def subscribe(self, msg_type: Any, topic: str, callback: Callable[[Any, Any], None], qos: QoSProfile) -> Any:
        """Subscribe to a topic of records: ``callback(message, message_info)`` for each message.

        The server takes these messages itself, outside rclpy's executor, which costs a fraction
        per message (docs/performance.md); callbacks run on the server's main thread, as executor
        callbacks do. Returns the subscription, for :meth:`unsubscribe` in ``on_cleanup``.
        """

    def unsubscribe(self, subscription: Any) -> None:
        """Destroy a subscription made by :meth:`subscribe`."""

    @property
    def worker(self) -> Worker:
        """Threads for slow parts of a plugin's work (saving an image, hashing a file): ``submit(job,
        on_done)`` runs ``job()`` on a thread and ``on_done(outcome)`` back on the main thread."""


class Measurement(abc.ABC):
    """Base class of measurement plugins."""

    Params: ClassVar[type] = NoParams
    schema_file: ClassVar[str | None] = None
    # True: collect() runs on the server's worker threads, so a collection that waits (a ping, a
    # subprocess, a file written) never holds up records, other measurements' timers or the
    # heartbeat. collect() must then not touch what callbacks on the main thread change without a
    # lock; the sample is gated, validated and published on the main thread.
    collect_in_worker: ClassVar[bool] = False
    schema_package: ClassVar[str] = "dc_measurements"

    def __init__(self, context: MeasurementContext, params: Any) -> None:
        self.context = context
        self.params = params

    @property
    def timer_driven(self) -> bool:
        """False for measurements that publish from events through ``context.emit``."""
        return True

    def on_configure(self) -> None:
        """Open what the plugin needs (files, subscriptions). Raise PluginError to fail configure."""

    def on_activate(self) -> None:
        """Called when the server activates, before the first collect."""

    def on_deactivate(self) -> None:
        """Called when the server deactivates; no collect follows until the next activate."""

    def on_cleanup(self) -> None:
        """Release what on_configure opened."""

    def counters(self) -> dict[str, int]:
        """Counters of the plugin's own (e.g. malformed input), served beside the server's for it."""
        return {}

    @abc.abstractmethod
    def collect(self) -> dict[str, Any] | None:
        """One sample as a JSON-able object, or None when there is nothing to report."""

    def collect_stamped(self) -> tuple[dict[str, Any] | None, int | None, str | None]:
        """``collect()`` with the sample's own stamp (ns) and group key when it has them.

        Plugins that forward records from elsewhere override this to keep the source's stamp;
        ``None`` means "now" and "the configured group_key".
        """
        return self.collect(), None, None

    def on_failed_validation(self, record: dict[str, Any], error: str) -> None:
        """Hook called when a record does not match the schema (after it was logged)."""

    @classmethod
    def load_schema(cls) -> dict[str, Any] | None:
        """The plugin's built-in JSON schema, or None if it has none."""
        if cls.schema_file is None:
            return None
        try:
            text = resources.files(cls.schema_package).joinpath("schemas", cls.schema_file).read_text()
        except (OSError, ModuleNotFoundError) as exc:
            raise PluginError(f"schema {cls.schema_file!r} of {cls.__name__} not found: {exc}") from exc
        schema: dict[str, Any] = json.loads(text)
        return schema
