"""The group server through `dc-bringup`, read as a user reads it: merged records on stdout."""

from __future__ import annotations

import socket
from itertools import pairwise
from pathlib import Path
from typing import Any

import pytest
import yaml

from tests.bringup_util import REPO, Bringup, dc

pytestmark = pytest.mark.e2e


def dummy(value: str, polling_interval: int, **extra: Any) -> dict[str, Any]:
    return {
        "plugin": "dc_measurements/Dummy",
        "record": f'{{"value": "{value}"}}',
        "polling_interval": polling_interval,
        **extra,
    }


def write_config(
    tmp_path: Path,
    measurements: dict[str, dict[str, Any]],
    groups: dict[str, dict[str, Any]],
    listen: str,
    group_server: dict[str, Any] | None = None,
    measurement_server: dict[str, Any] | None = None,
) -> Path:
    config = {
        "measurement_server": {
            "ros__parameters": {
                "measurement_plugins": list(measurements),
                "run_id": {"enabled": False},
                **(measurement_server or {}),
                **measurements,
            }
        },
        "group_server": {"ros__parameters": {"groups": list(groups), **(group_server or {}), **groups}},
        "destination_server": {
            "ros__parameters": {
                "destination_plugins": ["stdout"],
                "stdout": {"plugin": "dc_destinations/Stdout", "inputs": [listen]},
            }
        },
    }
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(config, sort_keys=False))
    return path


def free_port() -> int:
    """A loopback port nothing listens on now (dc status must know the port in advance)."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def body(record: dict[str, Any]) -> dict[str, Any]:
    """A delivered record without what the destination adds (its time key, a record id)."""
    return {k: v for k, v in record.items() if k not in ("date", "record_id")}


def gaps(records: list[dict[str, Any]]) -> list[float]:
    dates = [r["date"] for r in records]
    return [b - a for a, b in pairwise(dates)]


@pytest.mark.usefixtures("bringup_mode")
def test_example_5_cpu_and_memory_as_a_group(tmp_path: Path) -> None:
    with Bringup(REPO / "params" / "examples" / "example_5_fixed.yaml", tmp_path / "home") as run:
        records = run.wait_records(2, timeout=60)
    for record in records[:2]:
        # No group_key on the measurements: each record is nested under its topic's last segment.
        # run_id (the counter's, on by default) at the top level too, as in a measurement's record.
        assert set(body(record)) == {"cpu", "memory", "name", "run_id"}, record
        assert record["run_id"] == record["cpu"]["run_id"]
        assert record["name"] == "cpu_memory"
        assert "tags" not in record["cpu"] and "tags" not in record["memory"]
        assert record["cpu"]["name"] == "cpu" and record["memory"]["name"] == "memory"
        assert 0 <= record["memory"]["used"] <= 100
    assert 4.5 < gaps(records[:2])[0] < 5.5


@pytest.mark.usefixtures("bringup_mode")
def test_group_demo_memory_and_uptime(tmp_path: Path) -> None:
    with Bringup(REPO / "params" / "demos" / "group_memory_uptime_stdout.yaml", tmp_path / "home") as run:
        records = run.wait_records(3, timeout=60)
    for record in records[:3]:
        assert set(body(record)) == {"memory", "uptime", "run_id"}, record  # include_group_name: false
        assert set(record["uptime"]) >= {"time"} and set(record["memory"]) >= {"used"}
    # One record per uptime sample (every 3 s), dated by the set's stamps, not by publication.
    assert all(2.7 < g < 3.3 for g in gaps(records[:3])), gaps(records[:3])
    uptimes = [r["uptime"]["time"] for r in records[:3]]
    assert all(2 <= b - a <= 4 for a, b in pairwise(uptimes)), uptimes


def test_three_inputs_at_different_rates(tmp_path: Path) -> None:
    params = write_config(
        tmp_path,
        {
            "fast": dummy("fast", 500, group_key="f"),
            "medium": dummy("medium", 1000),
            "slow": dummy("slow", 2000),
        },
        {
            "trio": {
                "inputs": ["/dc/measurement/fast", "/dc/measurement/medium", "/dc/measurement/slow"],
                "sync_delay": 0.3,
                "tags": ["stdout"],
                "exclude_keys": ["*.name"],
            }
        },
        "/dc/group/trio",
    )
    with Bringup(params, tmp_path / "home") as run:
        records = run.wait_records(3, timeout=60)
    for record in records[:3]:
        assert body(record) == {
            # Each member says its measurement's schema version (docs/data-model.md).
            "f": {"value": "fast", "schema_version": 1},
            "medium": {"value": "medium", "schema_version": 1},
            "slow": {"value": "slow", "schema_version": 1},
            "name": "trio",
        }
    # One set per message of the slowest input.
    assert all(1.7 < g < 2.3 for g in gaps(records[:3])), gaps(records[:3])


def test_partial_records_when_one_input_stops(tmp_path: Path) -> None:
    params = write_config(
        tmp_path,
        {"steady": dummy("steady", 1000), "stops": dummy("stops", 1000, init_max_measurements=3)},
        {
            "pair": {
                "inputs": ["/dc/measurement/steady", "/dc/measurement/stops"],
                "sync_delay": 0.5,
                "sync_timeout": 1.5,
                "on_sync_timeout": "emit_partial",
                "tags": ["stdout"],
            }
        },
        "/dc/group/pair",
        group_server={"http_server": True, "http_port": free_port()},
        measurement_server={"http_server": True, "http_port": free_port()},
    )

    def partial_after_complete() -> list[dict[str, Any]]:
        records = sorted(run.records(), key=lambda r: r["date"])
        last_complete = max((i for i, r in enumerate(records) if "missing_inputs" not in r), default=None)
        return [] if last_complete is None else records[last_complete + 1 :]

    with Bringup(params, tmp_path / "home") as run:
        run.wait_until(lambda: len(partial_after_complete()) >= 3, 60, "3 partial records after a complete one")
        complete = [r for r in run.records() if "missing_inputs" not in r]
        partial = partial_after_complete()
        status = dc("status", "--params", str(params), env=run.env)
    # What an operator sees: the counters of each server that serves them, one table each.
    assert status.returncode == 0, status.stderr
    lines = status.stdout.splitlines()
    # The destination server's table first (every server's metrics endpoint is on by default).
    start = next(i for i, line in enumerate(lines) if line.startswith("group "))
    group_header, group_row, measurement_header, *measurement_rows = lines[start:]
    assert group_header.split()[:4] == ["group", "published", "partial", "dropped"]
    published, published_partial = (int(cell) for cell in group_row.split()[1:3])
    assert group_row.split()[0] == "pair" and published >= len(complete) and published_partial >= len(partial)
    assert measurement_header.split()[:3] == ["measurement", "collected", "published"]
    stops = next(row.split() for row in measurement_rows if row.startswith("stops "))
    # init_max_measurements 3: three published, then nothing more can be.
    assert stops[2] == "3" and stops[-2:] == ["-", "-"]  # no malformed/lost columns for a Dummy
    # Three samples of "stops" (a sample published before discovery completes may be lost).
    assert 1 <= len(complete) <= 3
    assert all(body(r) == {"steady": {"value": "steady", "name": "steady", "schema_version": 1},
                           "stops": {"value": "stops", "name": "stops", "schema_version": 1}, "name": "pair"}
               for r in complete)  # fmt: skip
    for record in partial:
        assert body(record) == {
            "steady": {"value": "steady", "name": "steady", "schema_version": 1},
            "missing_inputs": ["/dc/measurement/stops"],
            "name": "pair",
        }
    # Partial records keep the pace of the input that still publishes, dated by its stamps.
    assert all(0.8 < g < 1.2 for g in gaps(partial[:3])), gaps(partial[:3])


@pytest.mark.usefixtures("bringup_mode")
def test_a_group_is_the_input_of_another(tmp_path: Path) -> None:
    params = write_config(
        tmp_path,
        {
            "memory": {"plugin": "dc_measurements/Memory", "group_key": "memory", "polling_interval": 1000},
            "uptime": {"plugin": "dc_measurements/Uptime", "group_key": "uptime", "polling_interval": 1000},
            "extra": dummy("extra", 1000, group_key="extra"),
        },
        {
            "memory_uptime": {"inputs": ["/dc/measurement/memory", "/dc/measurement/uptime"], "sync_delay": 0.5},
            "system": {
                "inputs": ["/dc/group/memory_uptime", "/dc/measurement/extra"],
                "sync_delay": 0.5,
                "tags": ["stdout"],
                "exclude_keys": ["*.name", "memory_uptime.*.name"],
            },
        },
        "/dc/group/system",
    )
    with Bringup(params, tmp_path / "home") as run:
        records = run.wait_records(2, timeout=60)
    for record in records[:2]:
        assert set(body(record)) == {"memory_uptime", "extra", "name"}, record
        assert set(record["memory_uptime"]) == {"memory", "uptime"}
        assert record["extra"] == {"value": "extra", "schema_version": 1} and record["name"] == "system"
    assert all(0.8 < g < 1.2 for g in gaps(records[:2])), gaps(records[:2])
