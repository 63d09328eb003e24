"""What the seed's demos write in measurement_server beyond the documented parameters: accepted where it
means something, with a warning that says how DC reads it; a typo is still an error."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from dc_bringup.validate import validate_params_file
from dc_core.errors import ConfigError
from dc_measurements.config import CustomStrParam, parse_measurement_server
from dc_measurements.metadata import resolve_custom_params

UPTIME = {"measurement_plugins": ["uptime"], "uptime": {"plugin": "dc_measurements/Uptime"}}


def test_the_older_list_of_custom_str_params_takes_each_value_from_the_parameter_of_its_name() -> None:
    config = parse_measurement_server({**UPTIME, "custom_str_params": ["robot_name"], "robot_name": "C3PO"})
    assert config.custom_str_params == {"robot_name": CustomStrParam(name="robot_name", value="C3PO")}
    assert resolve_custom_params(config.custom_str_params) == [("robot_name", "C3PO", False)]
    (warning,) = config.warnings
    assert warning.startswith("measurement_server.custom_str_params: a list of ids is the older spelling")


def test_an_id_of_the_older_list_may_also_be_in_custom_str_params_list() -> None:
    config = parse_measurement_server(
        {**UPTIME, "custom_str_params": ["robot_name"], "robot_name": "C3PO", "custom_str_params_list": ["robot_name"]}
    )
    assert list(config.custom_str_params) == ["robot_name"]


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        ({"custom_str_params": ["robot_name"]}, "measurement_server.robot_name: missing"),
        ({"custom_str_params": ["robot_name"], "robot_name": 3}, "measurement_server.robot_name: expected a non-empty"),
        ({"custom_str_params": ["uptime"]}, "measurement_server.uptime: expected a non-empty string"),
        ({"custom_str_params": [["robot_name"]]}, "measurement_server.custom_str_params[0]: expected the id"),
        ({"custom_str_params": "robot_name"}, "measurement_server.custom_str_params: expected a mapping"),
        # A top-level string nothing refers to is still a typo to report.
        ({"robot_nmae": "C3PO"}, "measurement_server.robot_nmae: unknown parameter"),
        ({"save_local_base_path": "/data/=robot_name"}, "measurement_server.save_local_base_path: '=robot_name' names"),
        (
            {"save_local_base_path": "/data/=robot_name", "robot_name": ["C3PO"]},
            "measurement_server.save_local_base_path: '=robot_name' names no string parameter",
        ),
    ],
)
def test_errors_name_the_key(extra: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_measurement_server({**UPTIME, **extra})
    assert str(info.value).startswith(message)


def test_a_string_parameter_that_save_local_base_path_names_is_accepted() -> None:
    config = parse_measurement_server({**UPTIME, "save_local_base_path": "/data/={robot}/", "robot": "C3PO"})
    assert config.warnings == []


def test_destinations_in_the_server_section_are_ignored_with_a_warning() -> None:
    config = parse_measurement_server({**UPTIME, "destinations": {"minio": {"bucket": "mybucket"}}})
    assert config.warnings == [
        "measurement_server.destinations: ignored, as in the original (the bucket is the MinIO or S3 destination's)"
    ]


SEED_QR_SERVER = """
measurement_server:
  ros__parameters:
    custom_str_params: ["robot_name"]
    robot_name: "C3PO"
    measurement_plugins: ["uptime"]
    custom_str_params_list: ["robot_name"]
    custom_str_params:
      robot_name:
        name: robot_name
        value: "R2D2"
    destinations:
      minio:
        bucket: mybucket
    uptime:
      plugin: "dc_measurements/Uptime"
"""


def test_both_spellings_in_one_section_as_the_seed_qr_demo_writes_them(tmp_path: Path) -> None:
    # The key custom_str_params twice: YAML keeps the last, the mapping; robot_name beside it is left over.
    params = tmp_path / "params.yaml"
    params.write_text(SEED_QR_SERVER)
    report = validate_params_file(params)
    config = report.configs["measurement_server"]
    assert resolve_custom_params(config.custom_str_params) == [("robot_name", "R2D2", False)]
    assert any(w.startswith("measurement_server.robot_name: ignored") for w in report.warnings), report.warnings
    assert any(w.startswith("measurement_server.destinations: ignored") for w in report.warnings), report.warnings


def test_a_measurement_key_without_effect_is_said_once() -> None:
    config = parse_measurement_server(
        {"measurement_plugins": ["map"], "map": {"plugin": "dc_measurements/Map", "quiet": False}}
    )
    assert config.warnings == [
        "measurement_server.map.quiet: accepted for the original's files, has no effect because "
        "there is no map_saver output"
    ]
