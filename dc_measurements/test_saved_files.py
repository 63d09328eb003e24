"""Where saved files and their objects go: strftime in UTC by default (paths_timezone), Hive-style keys
(key_layout: hive), and the configure errors for a zone or layout that does not exist."""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import pytest

from dc_core.errors import ConfigError
from dc_measurements.config import parse_measurement_server
from dc_measurements.metadata import resolve_custom_params
from dc_measurements.saved_files import base_paths, file_locations

# 2026-03-01T03:30:00Z: still 28 February in California, already 04:30 in Paris.
MOMENT = 1_772_335_800.0


def locations(save_path: str = "map_%H%M", **node: Any) -> tuple[str, dict[str, str]]:
    section: dict[str, Any] = {
        "measurement_plugins": ["map"],
        "map": {"plugin": "dc_measurements/Uptime", "remote_keys": ["minio"], "remote_prefixes": ["maps"]},
        "save_local_base_path": "/data/%Y/%m/%d",
        "all_base_path": "=robot_name",
        "custom_str_params_list": ["robot_name"],
        "custom_str_params": {"robot_name": {"name": "robot_name", "value": "r2/d2"}},
        **node,
    }
    config = parse_measurement_server(section)
    paths = base_paths(section, config, resolve_custom_params(config.custom_str_params))
    common = config.measurements[0].common
    paths = dataclasses.replace(
        paths, remote_prefixes=dict(zip(common.remote_keys, common.remote_prefixes, strict=True))
    )
    found = file_locations(paths, save_path, MOMENT)
    return found.local, found.remote


def test_paths_and_keys_are_in_utc_by_default_whatever_the_robots_zone(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("TZ", "America/Los_Angeles")
    time.tzset()
    try:
        assert locations() == ("/data/2026/03/01/r2/d2/map_0330", {"minio": "r2/d2/maps/map_0330"})
        # The original's behaviour, asked for: the robot's local time (the previous day in California).
        assert locations(paths_timezone="local") == (
            "/data/2026/02/28/r2/d2/map_1930",
            {"minio": "r2/d2/maps/map_1930"},
        )
    finally:
        monkeypatch.delenv("TZ")
        time.tzset()
    assert locations(paths_timezone="Europe/Paris")[0] == "/data/2026/03/01/r2/d2/map_0430"


def test_hive_keys_partition_by_robot_and_utc_date_and_leave_the_local_path_alone() -> None:
    local, remote = locations(key_layout="hive")
    assert local == "/data/2026/03/01/r2/d2/map_0330"
    # The robot's name quoted: its "/" makes no folder, so robot= stays one partition.
    assert remote == {"minio": "maps/robot=r2%2Fd2/date=2026-03-01/map_0330"}


@pytest.mark.parametrize(
    ("node", "message"),
    [
        (
            {"paths_timezone": "Mars/Olympus_Mons"},
            "measurement_server.paths_timezone: .*no time zone is named 'Mars/Olympus_Mons'",
        ),
        ({"key_layout": "parquet"}, "measurement_server.key_layout: .*path.*hive"),
        (
            {"key_layout": "hive", "custom_str_params_list": [], "custom_str_params": {}, "all_base_path": ""},
            "measurement_server.key_layout: hive keys start with robot=<name>: add a custom string parameter robot_name",
        ),
    ],
)
def test_a_zone_or_layout_that_does_not_exist_is_a_configure_error(node: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        locations(**node)
