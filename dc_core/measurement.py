"""The measurement plugin contract.

A measurement is one small class: its parameters (a frozen dataclass, the type argument of its
base: ``class Cpu(Measurement[CpuParams])``, see dc_core.plugin), its JSON
schema (``schema_file`` in ``<schema_package>/schemas/``) and ``collect()``. Everything common —
timer, gating, validation, metadata, publishing — is done by the measurement server.

Timer-driven measurements return a record from :meth:`Measurement.collect` (or ``None`` when they
have nothing). Event-driven ones set ``timer_driven`` to false and call ``context.emit(record)``
from their subscription callbacks.
"""

from __future__ import annotations

import abc
import json
from dataclasses import dataclass, field
from importlib import resources
from typing import Any, ClassVar, Protocol

from dc_core.errors import PluginError
from dc_core.plugin import ParamsT, Plugin, PluginContext


@dataclass(frozen=True)
class BasePaths:
    """Expanded base paths of the measurement server, for plugins that save files."""

    save_local_base_path: str = ""
    all_base_path: str = ""
    remote_prefixes: dict[str, str] = field(default_factory=dict)


class MeasurementContext(PluginContext, Protocol):
    """What the measurement server gives a measurement plugin: the common ways in, and more."""

    @property
    def paths(self) -> BasePaths: ...
    def emit(self, record: dict[str, Any], *, stamp_ns: int | None = None, group_key: str | None = None) -> None:
        """Offer a record from an event (gated, validated and published like a collected one)."""


class Measurement(Plugin[ParamsT]):
    """Base class of measurement plugins."""

    schema_file: ClassVar[str | None] = None
    schema_package: ClassVar[str] = "dc_measurements"
    # True: collect() runs on the server's worker threads, so a collection that waits (a ping, a
    # subprocess, a file written) never holds up records, other measurements' timers or the
    # heartbeat. collect() must then not touch what callbacks on the main thread change without a
    # lock; the sample is gated, validated and published on the main thread.
    collect_in_worker: ClassVar[bool] = False
    context: MeasurementContext

    def __init__(self, context: MeasurementContext, params: ParamsT) -> None:
        super().__init__(context, params)

    @property
    def timer_driven(self) -> bool:
        """False for measurements that publish from events through ``context.emit``."""
        return True

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
