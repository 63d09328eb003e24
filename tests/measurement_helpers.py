"""What the tests of several measurement plugins share: a configured plugin, schema checks, waiting."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jsonschema

from dc_core.measurement import Measurement
from dc_core.params import parse_params
from dc_core.testing import FakeContext


def configured(cls: type[Measurement[Any]], measurement_id: str = "m", /, **values: Any) -> Any:
    params: Any = parse_params(cls.Params, values, f"measurement_server.{measurement_id}")
    plugin = cls(FakeContext(measurement_id), params)
    plugin.on_configure()
    plugin.on_activate()
    return plugin


def assert_valid(cls: type[Measurement[Any]], record: dict[str, Any]) -> None:
    schema = cls.load_schema()
    assert schema is not None
    jsonschema.Draft7Validator(schema).validate(record)


def wait_until(predicate: Callable[[], bool], timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError("condition not reached in time")
        time.sleep(0.02)


def meminfo() -> dict[str, int]:
    values = {}
    for line in Path("/proc/meminfo").read_text().splitlines():
        key, rest = line.split(":", 1)
        values[key] = int(rest.split()[0]) * 1024
    return values
