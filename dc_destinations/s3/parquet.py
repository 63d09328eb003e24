"""The S3 destination's Parquet objects (``format: parquet``): one object per batch and measurement.

A data team queries the bucket with DuckDB, Athena or pyarrow without a conversion job, so each
object is a table a query engine reads as it is: one row per record, one column per flattened key
(``cpu.average``, ``sorted.0.pid``: objects and arrays walked as ``dc_core.jsonpath.flatten`` walks
them, joined by ``.``), zstd-compressed. The columns' types come from the measurement's JSON schema
(its ``schema.json``), so that every object of a measurement has the same type for a key whatever
values a batch happened to hold (an ``integer`` key stays int64 in a batch of zeros, a ``number``
key float64 in a batch of whole numbers); a key the schema does not type (DC's own keys, a
measurement without a schema, an open object) takes the type its values in the batch have. A value
that cannot have its column's type (a text where the schema says a number: a record that broke its
schema) makes that record rejected alone, with the key named.
"""

from __future__ import annotations

import io
import json
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from dc_core.errors import ConfigError, PluginError
from dc_core.jsonpath import declared_types_at, flatten

INSTALL_HINT = "format: parquet needs pyarrow: pip install 'ros2-dc[parquet]'"
# The column types a JSON schema's types map to; a column of kind "json" holds JSON text.
_OF_SCHEMA = {"integer": "int64", "number": "float64", "boolean": "bool", "string": "string"}


def pyarrow_missing() -> str | None:
    try:
        import pyarrow.parquet  # noqa: F401
    except ImportError:
        return INSTALL_HINT
    return None


class MeasurementSchemas:
    """The JSON schema of each measurement, by the records' ``name``.

    ``configured`` maps a name to a measurement plugin type (``dc_measurements/Cpu``) or a schema
    file; checked at configure. Any other name is looked up among the measurement plugins whose type
    ends with it (``cpu`` is ``dc_measurements/Cpu``), once; none found: the values' own types.
    """

    def __init__(self, configured: Mapping[str, str], path: str) -> None:
        self._schemas: dict[str, dict[str, Any] | None] = {}
        for name, source in configured.items():
            try:
                self._schemas[name] = _load(source)
            except (OSError, ValueError, PluginError) as exc:
                raise ConfigError(f"{path}.{name}", f"no JSON schema from {source!r}: {exc}") from None

    def of(self, name: str) -> dict[str, Any] | None:
        if name not in self._schemas:
            self._schemas[name] = _builtin(name)
        return self._schemas[name]


def _load(source: str) -> dict[str, Any] | None:
    if "/" in source and not source.endswith(".json"):
        from dc_core.plugins import load_plugin

        schema: dict[str, Any] | None = load_plugin("measurements", source).load_schema()  # type: ignore[attr-defined]
        return schema
    loaded = json.loads(Path(source).expanduser().read_text())
    if not isinstance(loaded, dict):
        raise ValueError("not a JSON object")
    return loaded


def _builtin(name: str) -> dict[str, Any] | None:
    from dc_core.plugins import list_plugins

    for info in list_plugins("measurements"):
        if info.name.rpartition("/")[2].lower() == name.lower():
            try:
                return _load(info.name)
            except (PluginError, OSError, ValueError):
                return None  # a plugin that cannot load here (its extra missing): the values' types
    return None


class Unfit(Exception):
    """A record's value cannot have its column's type: that record is rejected alone."""


def encode(
    records: Sequence[tuple[int, Mapping[str, Any]]],
    schema: dict[str, Any] | None,
    reject: Callable[[int, str], None],
) -> tuple[list[int], bytes] | None:
    """One Parquet object of ``records`` ((batch index, record) pairs of one measurement): the indexes
    it holds and its bytes; ``reject(index, reason)`` for a record that fits no column; None if none fit."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    # "/"-paths for the schema; the columns join the same parts with ".".
    rows = [(index, flatten(record)) for index, record in records]
    paths: dict[str, None] = {}
    for _, flat in rows:
        paths.update(dict.fromkeys(flat))
    kinds = {path: _kind(path, schema, [flat.get(path) for _, flat in rows]) for path in paths}
    kept: list[int] = []
    columns: dict[str, list[Any]] = {path: [] for path in paths}
    for index, flat in rows:
        try:
            values = {path: _fit(flat.get(path), kinds[path], path) for path in paths}
        except Unfit as exc:
            reject(index, str(exc))
            continue
        kept.append(index)
        for path, value in values.items():
            columns[path].append(value)
    if not kept:
        return None
    types = {
        "int64": pa.int64(),
        "float64": pa.float64(),
        "bool": pa.bool_(),
        "string": pa.string(),
        "json": pa.string(),
    }
    arrays = [pa.array(columns[path], type=types[kinds[path]]) for path in paths]
    names = [path[1:].replace("/", ".") for path in paths]
    buffer = io.BytesIO()
    pq.write_table(pa.Table.from_arrays(arrays, names=names), buffer, compression="zstd")
    return kept, buffer.getvalue()


def _kind(path: str, schema: dict[str, Any] | None, values: list[Any]) -> str:
    """The column's type: the schema's when it names one, else the values' (mixed: JSON text)."""
    declared = declared_types_at(schema, path) if schema is not None else None
    if declared:
        types = declared - {"null"}
        if types == {"integer", "number"}:
            types = {"number"}
        if len(types) == 1 and next(iter(types)) in _OF_SCHEMA:
            return _OF_SCHEMA[types.pop()]
    seen = {_value_kind(v) for v in values if v is not None}
    if seen == {"int64", "float64"}:
        return "float64"
    return seen.pop() if len(seen) == 1 else "json" if seen else "string"


def _value_kind(value: Any) -> str:
    if isinstance(value, bool):
        return "bool"
    if isinstance(value, int):
        return "int64"
    if isinstance(value, float):
        return "float64"
    if isinstance(value, str):
        return "string"
    return "json"  # an empty object or array: a leaf of flatten


def _fit(value: Any, kind: str, path: str) -> Any:
    if value is None:
        return None
    if kind == "json":
        return json.dumps(value, separators=(",", ":"), ensure_ascii=False)
    have = _value_kind(value)
    if have == kind or (kind == "float64" and have == "int64"):
        return value
    raise Unfit(f"{path[1:].replace('/', '.')} is {json.dumps(value)[:40]}, not the {kind} its schema says")
