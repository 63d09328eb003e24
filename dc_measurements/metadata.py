"""Measurement-server-wide record metadata: run id and custom string parameters."""

from __future__ import annotations

import os
import uuid
from pathlib import Path
from typing import Any

from dc_core.errors import ConfigError
from dc_core.paths import expand_env
from dc_measurements.config import CustomStrParam, RunIdParams


def next_run_id(params: RunIdParams, path: str = "measurement_server.run_id") -> str | None:
    """The run id of this start: counter file incremented (created with 1), or a UUID, or None."""
    if not params.enabled:
        return None
    if params.uuid:
        return str(uuid.uuid4())
    if not params.counter:
        return None
    counter_file = Path(expand_env(params.counter_path, f"{path}.counter_path"))
    previous = 0
    try:
        text = counter_file.read_text().strip()
        previous = int(text) if text else 0
    except FileNotFoundError:
        previous = 0
    except ValueError as exc:
        raise ConfigError(f"{path}.counter_path", f"{counter_file} does not hold an integer") from exc
    current = previous + 1
    counter_file.parent.mkdir(parents=True, exist_ok=True)
    # Write then rename so a crash never leaves a half-written counter.
    tmp = counter_file.with_name(counter_file.name + ".tmp")
    tmp.write_text(f"{current}\n")
    os.replace(tmp, counter_file)
    return str(current)


def resolve_custom_params(
    custom: dict[str, CustomStrParam], path: str = "measurement_server"
) -> list[tuple[str, str, bool]]:
    """(key, value, force_override) per custom parameter; files are read once, here."""
    out = []
    for cid, spec in custom.items():
        value = spec.value
        if not value:
            file = expand_env(spec.value_from_file, f"{path}.custom_str_params.{cid}.value_from_file")
            try:
                value = Path(file).read_text()
            except OSError as exc:
                raise ConfigError(
                    f"{path}.custom_str_params.{cid}.value_from_file", f"cannot read {file}: {exc.strerror}"
                ) from exc
            if value.endswith("\n"):
                value = value[:-1]
        out.append((spec.name, value, spec.force_override))
    return out


def apply_metadata(
    record: dict[str, Any],
    *,
    run_id: str | None,
    tags: list[str],
    name: str | None,
    plugin: str | None,
    custom: list[tuple[str, str, bool]],
    schema_version: int | None = None,
) -> dict[str, Any]:
    if run_id is not None:
        record["run_id"] = run_id
    if schema_version is not None:
        record["schema_version"] = schema_version
    if tags:
        record["tags"] = list(tags)
    if name is not None:
        record["name"] = name
    if plugin is not None:
        record["plugin"] = plugin
    for key, value, force in custom:
        if force or key not in record:
            record[key] = value
    return record
