"""System measurements through `dc-bringup`: the seed's example 4 as printed, and DC's default job.

Every record that arrives is checked against its plugin's JSON schema once the metadata DC adds
(`date`, `name`, `run_id`, `record_id`) is taken off: what users receive is what the schema documents.
"""

from __future__ import annotations

import itertools
import json
from pathlib import Path
from typing import Any, cast

import jsonschema
import pytest

from dc_core.measurement import Measurement
from dc_core.plugins import load_plugin
from tests.bringup_util import REPO, Bringup

pytestmark = pytest.mark.e2e

# Added by DC after collection: `name` and `run_id` by the measurement server, `date` and
# `record_id` by the destination server.
METADATA = ("date", "name", "run_id", "record_id", "schema_version")
DEFAULT_JOB = {
    "cpu": "dc_measurements/Cpu",
    "memory": "dc_measurements/Memory",
    "storage": "dc_measurements/Storage",
    "uptime": "dc_measurements/Uptime",
    "os": "dc_measurements/OS",
    "network": "dc_measurements/Network",
}


def assert_matches_schema(plugin: str, record: dict[str, Any]) -> None:
    measurement = cast(type[Measurement[Any]], load_plugin("measurements", plugin))
    schema = measurement.load_schema()
    assert schema is not None, f"{plugin} has no schema"
    sample = {key: value for key, value in record.items() if key not in METADATA}
    jsonschema.Draft7Validator(schema).validate(sample)
    for key in schema.get("required", []):
        assert key in record, f"{plugin}: {key} missing"


def by_name(records: list[dict[str, Any]], name: str) -> list[dict[str, Any]]:
    return [r for r in records if r.get("name") == name]


def test_example_4_cpu_and_memory_every_five_seconds(tmp_path: Path) -> None:
    example = REPO / "params" / "examples" / "example_4.yaml"
    with Bringup(example, tmp_path) as run:
        # Collected at activation, then every 5 s: two of each after ~5 s.
        run.wait_until(
            lambda: all(len(by_name(run.records(), name)) >= 2 for name in ("cpu", "memory")), 40, "two of each"
        )
        records = run.records()
    for name, plugin in (("cpu", "dc_measurements/Cpu"), ("memory", "dc_measurements/Memory")):
        mine = by_name(records, name)
        assert len(mine) >= 2, records
        for record in mine:
            assert_matches_schema(plugin, record)
            assert record["run_id"] == "1"
            assert "tags" not in record
        gaps = [b["date"] - a["date"] for a, b in itertools.pairwise(mine)]
        assert all(4.5 < gap < 5.5 for gap in gaps), gaps
    cpu = by_name(records, "cpu")[0]
    assert 0.0 <= cpu["average"] <= 100.0 and cpu["processes"] > 0
    assert 0.0 < by_name(records, "memory")[0]["used"] < 100.0


@pytest.mark.usefixtures("bringup_mode")
def test_default_job_delivers_every_system_measurement_to_stdout_and_file(tmp_path: Path) -> None:
    home = tmp_path / "home"
    jsonl = home / "var" / "dc" / "records" / "system.jsonl"

    def file_records() -> list[dict[str, Any]]:
        if not jsonl.exists():
            return []
        return [json.loads(line) for line in jsonl.read_text().splitlines() if line.strip()]

    def all_names(records: list[dict[str, Any]]) -> bool:
        return set(DEFAULT_JOB) <= {r.get("name") for r in records}

    with Bringup(REPO / "params" / "default.yaml", home) as run:
        run.wait_until(lambda: all_names(run.records()), 40, "a record of each measurement on stdout")
        run.wait_until(lambda: all_names(file_records()), 20, f"a record of each measurement in {jsonl}")
    on_stdout = run.records()
    in_file = file_records()
    for name, plugin in DEFAULT_JOB.items():
        for record in by_name(on_stdout, name) + by_name(in_file, name):
            assert_matches_schema(plugin, record)
            assert record["run_id"] == "1"
    # Both destinations received the same records: the file holds what stdout printed.
    first_on_stdout = {name: by_name(on_stdout, name)[0] for name in DEFAULT_JOB}
    first_in_file = {name: by_name(in_file, name)[0] for name in DEFAULT_JOB}
    assert first_in_file == first_on_stdout
    assert (home / "var" / "dc" / "run_id").read_text().strip() == "1"
    assert first_on_stdout["network"]["online"] is True, "127.0.0.1 answers"
    assert first_on_stdout["storage"]["capacity"] > 0
    assert run.returncode == 0
