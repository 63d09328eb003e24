"""Memory measurement, compared with /proc/meminfo read here."""

from __future__ import annotations

import pytest

from dc_measurements.memory import Memory
from tests.measurement_helpers import assert_valid, configured, meminfo


def test_memory_used_counts_available_memory_as_free() -> None:
    record = configured(Memory).collect()
    assert_valid(Memory, record)
    info = meminfo()
    expected = (info["MemTotal"] - info["MemAvailable"]) / info["MemTotal"] * 100
    assert record["used"] == pytest.approx(expected, abs=2.0)
