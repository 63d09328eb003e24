"""OS measurement, compared with os-release, os.uname and sysconf read here."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from dc_measurements.os_info import OperatingSystem
from tests.measurement_helpers import assert_valid, configured


def os_release_pretty_name() -> str:
    for candidate in ("/etc/os-release", "/usr/lib/os-release"):
        if os.path.exists(candidate):
            for line in Path(candidate).read_text().splitlines():
                if line.startswith("PRETTY_NAME="):
                    return line.split("=", 1)[1].strip().strip('"')
    pytest.skip("no os-release on this machine")


def test_os_reports_distribution_kernel_cpus_and_memory() -> None:
    record = configured(OperatingSystem).collect()
    assert_valid(OperatingSystem, record)
    assert record["os"] == os_release_pretty_name()
    assert record["kernel"] == os.uname().release
    assert record["cpus"] == os.cpu_count()
    physical = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE") / 1024**3
    assert record["memory"] == pytest.approx(physical, abs=0.01)
