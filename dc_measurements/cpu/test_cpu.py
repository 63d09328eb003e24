"""Cpu measurement, compared with /proc/<pid>/stat of a busy child process the test starts."""

from __future__ import annotations

import os
import pwd
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from dc_measurements.cpu import Cpu
from tests.measurement_helpers import assert_valid, configured, wait_until


def process_ticks(pid: int) -> int:
    # Fields after the command name (which may contain spaces): utime and stime are 14th and 15th.
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return int(fields[11]) + int(fields[12])


def machine_busy_and_total() -> tuple[int, int]:
    values = [int(v) for v in Path("/proc/stat").read_text().splitlines()[0].split()[1:]]
    # user nice system idle iowait irq softirq steal (guest time is already inside user/nice)
    total = sum(values[:8])
    return total - values[3] - values[4], total


def proc_process_count() -> int:
    return sum(1 for entry in os.listdir("/proc") if entry.isdigit())


@pytest.fixture
def busy_child() -> Iterator[subprocess.Popen[bytes]]:
    child = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        yield child
    finally:
        child.kill()
        child.wait()


def test_cpu_reports_a_busy_process_with_its_usage(busy_child: subprocess.Popen[bytes]) -> None:
    ticks_per_second = os.sysconf("SC_CLK_TCK")
    busy_before, total_before = machine_busy_and_total()
    child_before, wall_before = process_ticks(busy_child.pid), time.monotonic()
    plugin = configured(Cpu, max_processes=10000, cpu_min=0.0)  # on_activate starts the window
    wait_until(lambda: process_ticks(busy_child.pid) - child_before >= ticks_per_second // 2)
    record = plugin.collect()
    child_after, wall_after = process_ticks(busy_child.pid), time.monotonic()
    busy_after, total_after = machine_busy_and_total()

    assert_valid(Cpu, record)
    expected_average = (busy_after - busy_before) / (total_after - total_before) * 100
    assert record["average"] > 0
    assert record["average"] == pytest.approx(expected_average, abs=15)
    assert record["processes"] == pytest.approx(proc_process_count(), abs=30)

    mine = [p for p in record["sorted"] if p["pid"] == busy_child.pid]
    assert len(mine) == 1
    child = mine[0]
    expected_cpu = (child_after - child_before) / ticks_per_second / (wall_after - wall_before) * 100
    assert child["cpu"] == pytest.approx(expected_cpu, abs=20)
    assert child["user"] == pwd.getpwuid(os.getuid()).pw_name
    assert "while True" in child["cmd"]
    rss_kib = next(
        int(line.split()[1])
        for line in Path(f"/proc/{busy_child.pid}/status").read_text().splitlines()
        if line.startswith("VmRSS:")
    )
    assert child["ram"] == pytest.approx(rss_kib, abs=2048)
    assert 0 <= child["uptime"] <= wall_after - wall_before + 5

    cpus = [p["cpu"] for p in record["sorted"]]
    assert cpus == sorted(cpus, reverse=True)
    assert max(cpus) <= 100 * (os.cpu_count() or 1) + 5


def test_cpu_first_sample_is_not_a_meaningless_zero(busy_child: subprocess.Popen[bytes]) -> None:
    plugin = configured(Cpu, max_processes=-1)
    start = process_ticks(busy_child.pid)
    wait_until(lambda: process_ticks(busy_child.pid) - start >= 20)
    assert plugin.collect()["average"] > 0


def test_cpu_limits_and_filters_the_process_list() -> None:
    assert "sorted" not in configured(Cpu, max_processes=-1).collect()
    assert len(configured(Cpu, max_processes=3, cpu_min=-1.0).collect()["sorted"]) == 3
    assert len(configured(Cpu, max_processes=2, cpu_min=0.0).collect()["sorted"]) <= 2
    assert configured(Cpu, max_processes=0).collect()["sorted"] == []
    record = configured(Cpu, max_processes=50, cpu_min=30.0).collect()
    assert_valid(Cpu, record)
    assert all(p["cpu"] >= 30.0 for p in record["sorted"])


def test_two_cpu_measurements_do_not_share_their_window(busy_child: subprocess.Popen[bytes]) -> None:
    first = configured(Cpu, "cpu_a", max_processes=-1)
    second = configured(Cpu, "cpu_b", max_processes=-1)
    start = process_ticks(busy_child.pid)
    wait_until(lambda: process_ticks(busy_child.pid) - start >= 20)
    assert first.collect()["average"] > 0
    # A collect of one instance does not reset the other's averaging window.
    assert second.collect()["average"] > 0


def test_cpu_sample_taken_at_activation_is_not_zero(busy_child: subprocess.Popen[bytes]) -> None:
    plugin = configured(Cpu, max_processes=-1)  # configured and activated
    # At once, as the measurement server's first collect after activation: a busy child is running.
    assert plugin.collect()["average"] > 0
