"""The measurement plugin contract.

A measurement is one small class: its parameters (a frozen dataclass, the type argument of its
base: ``class Cpu(Measurement[CpuParams])``, see dc_core.plugin), its JSON
schema (``schema.json`` beside its module) and ``collect()``. Everything common —
timer, gating, validation, metadata, publishing — is done by the measurement server.

Timer-driven measurements return a record from :meth:`Measurement.collect` (or ``None`` when they
have nothing). Event-driven ones set ``timer_driven`` to false and call ``context.emit(record)``
from their subscription callbacks.
"""

from __future__ import annotations

import abc
import datetime as dt
import json
import sys
from dataclasses import dataclass, field
from importlib import resources
from importlib.resources.abc import Traversable
from pathlib import Path
from typing import Any, ClassVar, Protocol

from dc_core.errors import PluginError
from dc_core.plugin import ParamsT, Plugin, PluginContext


@dataclass(frozen=True)
class BasePaths:
    """Expanded base paths of the measurement server, for plugins that save files."""

    save_local_base_path: str = ""
    all_base_path: str = ""
    remote_prefixes: dict[str, str] = field(default_factory=dict)
    # The zone strftime tokens are expanded in (measurement_server.paths_timezone); None: local time.
    zone: dt.tzinfo | None = dt.UTC
    # Folders after the remote prefix in every object key instead of all_base_path, strftime tokens
    # included (measurement_server.key_layout: hive gives "robot=<name>/date=%Y-%m-%d"); empty: none.
    key_partitions: str = ""


class MeasurementContext(PluginContext, Protocol):
    """What the measurement server gives a measurement plugin: the common ways in, and more."""

    @property
    def paths(self) -> BasePaths: ...
    def emit(self, record: dict[str, Any], *, stamp_ns: int | None = None, group_key: str | None = None) -> None:
        """Offer a record from an event (gated, validated and published like a collected one)."""


class Measurement(Plugin[ParamsT]):
    """Base class of measurement plugins."""

    # The JSON schema (draft-07) of the plugin's own fields, beside its module: a plugin folder
    # holds ``schema.json``. None: the plugin has no schema (its records are someone else's).
    schema_file: ClassVar[str | None] = "schema.json"
    # True: collect() runs on the server's worker threads, so a collection that waits (a ping, a
    # subprocess, a file written) never holds up records, other measurements' timers or the
    # heartbeat. collect() must then not touch what callbacks on the main thread change without a
    # lock; the sample is gated, validated and published on the main thread.
    collect_in_worker: ClassVar[bool] = False
    # True: every sample is a record dc_core.records.parse_record returned (JSON's own types only),
    # so the server writes it with orjson (dump_parsed, ~0.7 us) rather than json (~3.4 us); the
    # text is the same. A sample holding anything else (a NaN, a tuple, a UUID) must leave it False.
    samples_are_parsed_json: ClassVar[bool] = False
    # True: the measurement's conditions are its trigger, not a gate. Each poll the server calls
    # on_poll() with whether they hold (None: it has none) and never collect(); the records the plugin
    # emits are published whatever the conditions say then (an incident recorded after the robot
    # moved on is still an incident).
    conditions_trigger: ClassVar[bool] = False
    # Set by the server before on_configure for a conditions_trigger measurement: whether it has
    # conditions to judge at each poll (without any, it may poll itself only when it has work).
    has_trigger_conditions: bool = True
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

    def on_poll(self, conditions_met: bool | None) -> None:
        """One polling period of a ``conditions_trigger`` measurement, on the main thread."""

    def record_bytes_estimate(self) -> int | None:
        """The usual size of a record in bytes, for a plugin whose records are large (images in base64).

        The output topic's history starts as deep as ``history_bytes`` allows for records of this
        size, instead of ``history_depth``; either way it shrinks when a larger record is published
        (dc_core.record_history). None: small records.
        """
        return None

    def on_failed_validation(self, record: dict[str, Any], error: str) -> None:
        """Hook called when a record does not match the schema (after it was logged)."""

    def on_published(self, sample: dict[str, Any]) -> None:
        """Called on the main thread once the record of ``sample`` (the object collect() or emit() gave) was
        published: the place for side effects that only a published record should have, such as writing the
        files it points to (hand slow work to ``context.worker``). A sample the conditions, a limit or the
        validation dropped gets no call."""

    @classmethod
    def load_schema(cls) -> dict[str, Any] | None:
        """The plugin's built-in JSON schema, or None if it has none.

        The default ``schema.json`` is optional (a plugin written without a schema has none); a
        file named on purpose must exist.
        """
        if cls.schema_file is None:
            return None
        path = schema_path(cls)
        try:
            text = path.read_text()
        except FileNotFoundError:
            if cls.schema_file == Measurement.schema_file:
                return None
            raise PluginError(f"schema {cls.schema_file!r} of {cls.__name__} not found at {path}") from None
        except OSError as exc:
            raise PluginError(f"schema {cls.schema_file!r} of {cls.__name__} cannot be read: {exc}") from exc
        try:
            schema: dict[str, Any] = json.loads(text)
        except ValueError as exc:
            raise PluginError(f"schema {path} of {cls.__name__} is not JSON: {exc}") from exc
        return schema


def schema_path(cls: type[Measurement[Any]]) -> Traversable:
    """Where a measurement's ``schema_file`` is: in the folder of the module that defines the class."""
    module = sys.modules[cls.__module__]
    is_package = getattr(module, "__path__", None) is not None
    package = cls.__module__ if is_package else cls.__module__.rpartition(".")[0]
    if not package:  # a module of no package (a script, a test file run as a module): its own folder
        return Path(getattr(module, "__file__", None) or ".").resolve().parent / (cls.schema_file or "")
    return resources.files(package).joinpath(cls.schema_file or "")
