"""destination_server configuration: what parses, and the errors and warnings a user gets (no ROS)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import yaml

from dc_core.config import load_params_file
from dc_core.errors import ConfigError
from dc_destinations.config import parse_destination_server
from dc_destinations.file import File
from dc_destinations.null import Null
from dc_destinations.rcl import Rcl
from dc_destinations.stdout import Stdout

UPTIME = "/dc/measurement/uptime"


def stdout_section(**extra: Any) -> dict[str, Any]:
    return {
        "destination_plugins": ["flb_stdout"],
        "flb_stdout": {"plugin": "dc_destinations/FlbStdout", "inputs": [UPTIME], **extra},
    }


def error_of(section: dict[str, Any]) -> ConfigError:
    with pytest.raises(ConfigError) as info:
        parse_destination_server(section)
    return info.value


def test_seed_example_1_parses_with_defaults() -> None:
    config = parse_destination_server(stdout_section())
    (dest,) = config.destinations
    assert dest.name == "flb_stdout"
    assert dest.plugin_class is Stdout
    assert (dest.common.time_format, dest.common.time_key, dest.common.debug) == ("double", "date", False)
    assert dest.delivery.batch_size >= 1
    assert config.names == ["flb_stdout"]
    assert config.inputs == {UPTIME}
    assert config.node.flb.flush == 1.0
    assert config.warnings == []


@pytest.mark.parametrize(
    ("plugin", "cls"),
    [
        ("dc_destinations/Stdout", Stdout),
        ("dc_destinations/FlbStdout", Stdout),
        ("dc_destinations/File", File),
        ("dc_destinations/FlbFile", File),
        ("dc_destinations/Null", Null),
        ("dc_destinations/FlbNull", Null),
        ("dc_destinations/Rcl", Rcl),
    ],
)
def test_plugin_names_and_flb_aliases(plugin: str, cls: type) -> None:
    section = {"destination_plugins": ["d"], "d": {"plugin": plugin, "inputs": [UPTIME]}}
    assert parse_destination_server(section).destinations[0].plugin_class is cls


def test_several_destinations_union_of_inputs() -> None:
    section = {
        "destination_plugins": ["out", "disk"],
        "out": {"plugin": "dc_destinations/Stdout", "inputs": [UPTIME, "/dc/measurement/cpu"]},
        "disk": {"plugin": "dc_destinations/File", "inputs": [UPTIME], "path": "/tmp/x", "format": "csv"},
    }
    config = parse_destination_server(section)
    assert config.names == ["out", "disk"]
    assert config.inputs == {UPTIME, "/dc/measurement/cpu"}
    assert config.destinations[1].plugin_params.format == "csv"


def test_common_delivery_and_plugin_params_share_one_section() -> None:
    section = stdout_section(time_format="iso8601", time_key="ts", debug=True, batch_size=10, format="json_lines")
    (dest,) = parse_destination_server(section).destinations
    assert (dest.common.time_format, dest.common.time_key, dest.common.debug) == ("iso8601", "ts", True)
    assert dest.delivery.batch_size == 10
    assert dest.plugin_params.format == "json_lines"


def test_fluent_bit_json_date_names_set_the_time_key() -> None:
    # The seed's FlbStdout example configures the time key with Fluent Bit's stdout options.
    (dest,) = parse_destination_server(
        stdout_section(format="json", json_date_key="when", json_date_format="iso8601")
    ).destinations
    assert (dest.common.time_key, dest.common.time_format) == ("when", "iso8601")


@pytest.mark.parametrize(
    ("section", "path", "message"),
    [
        (
            stdout_section(time_fromat="double"),
            "destination_server.flb_stdout.time_fromat",
            'did you mean "time_format"',
        ),
        (stdout_section(fromat="json"), "destination_server.flb_stdout.fromat", 'did you mean "format"'),
        (
            stdout_section(batch_sise=3),
            "destination_server.flb_stdout.batch_sise",
            'did you mean "batch_size"',
        ),
        (
            stdout_section(debug="very"),
            "destination_server.flb_stdout.debug",
            'expected a boolean, got "very"',
        ),
        (
            stdout_section(time_format="epoch"),
            "destination_server.flb_stdout.time_format",
            '"double", "iso8601"',
        ),
        (stdout_section(inputs="/dc/x"), "destination_server.flb_stdout.inputs", "expected a list of string"),
        (stdout_section(inputs=[]), "destination_server.flb_stdout.inputs", "at least one topic"),
        (
            stdout_section(batch_size=0),
            "destination_server.flb_stdout.batch_size",
            "expected an integer >= 1",
        ),
        (
            stdout_section(plugin="dc_destinations/FlbStdot"),
            "destination_server.flb_stdout.plugin",
            "unknown destination plugin 'dc_destinations/FlbStdot' (did you mean \"dc_destinations/FlbStdout\"?)",
        ),
        (
            {"destination_plugins": ["d"], "d": {"plugin": "dc_destinations/Null"}},
            "destination_server.d.inputs",
            "required parameter missing (expected list of string)",
        ),
        (
            {"destination_plugins": ["d"], "d": {"inputs": [UPTIME]}},
            "destination_server.d.plugin",
            "required parameter missing",
        ),
        ({"destination_plugins": ["d"]}, "destination_server.d", "section missing"),
        (
            {"destination_plugins": ["d", "d"], "d": {"plugin": "dc_destinations/Null", "inputs": [UPTIME]}},
            "destination_server.destination_plugins",
            "'d' is listed twice",
        ),
        (
            {**stdout_section(), "destination_plugin": ["flb_stdout"]},
            "destination_server.destination_plugin",
            'did you mean "destination_plugins"',
        ),
        ({**stdout_section(), "flb": {"flsh": 1}}, "destination_server.flb.flsh", 'did you mean "flush"'),
        ({**stdout_section(), "flb": {"flush": "soon"}}, "destination_server.flb.flush", "expected a number"),
        (
            {**stdout_section(), "flb": {"intake_queue_limit_bytes": "lots"}},
            "destination_server.flb.intake_queue_limit_bytes",
            'expected a size such as "64M"',
        ),
        ({**stdout_section(), "flb": "fast"}, "destination_server.flb", "expected a mapping"),
        (
            {**stdout_section(), "flb": {"buffer_check_interval": -1}},
            "destination_server.flb.buffer_check_interval",
            "expected a number >= 0",
        ),
        (
            stdout_section(dead_letter_limit_size="lots"),
            "destination_server.flb_stdout.dead_letter_limit_size",
            'expected a size such as "500M"',
        ),
    ],
    ids=[
        "unknown common key",
        "unknown plugin key",
        "unknown delivery key",
        "wrong type",
        "not a choice",
        "inputs not a list",
        "inputs empty",
        "below minimum",
        "unknown plugin",
        "missing inputs",
        "missing plugin",
        "section missing",
        "listed twice",
        "unknown node key",
        "unknown flb key",
        "flb wrong type",
        "intake byte limit not a size",
        "flb not a mapping",
        "check interval below 0",
        "dead letter limit not a size",
    ],
)
def test_errors_name_the_yaml_path(section: dict[str, Any], path: str, message: str) -> None:
    error = error_of(section)
    assert error.path == path
    assert message in error.message


def test_unknown_plugin_parameter_error_names_the_plugin() -> None:
    error = error_of(stdout_section(colour="red"))
    assert error.message.startswith("unknown parameter of dc_destinations/FlbStdout")


def test_file_plugin_own_parameters_checked() -> None:
    section = {
        "destination_plugins": ["disk"],
        "disk": {"plugin": "dc_destinations/FlbFile", "inputs": [UPTIME], "format": "xml"},
    }
    error = error_of(section)
    assert error.path == "destination_server.disk.format"
    assert '"json"' in error.message


def test_flb_numbers_written_as_strings_as_in_the_seed_reference() -> None:
    section = {**stdout_section(), "flb": {"flush": "3", "scheduler_cap": "2000", "http_port": "2021"}}
    flb = parse_destination_server(section).node.flb
    assert (flb.flush, flb.scheduler_cap, flb.http_port) == (3.0, 2000.0, 2021)


@pytest.mark.parametrize(
    "section",
    [
        {**stdout_section(), "flb": {"flush": 1, "flb_grace": 4}},
        {**stdout_section(), "flb": {"flush": 1}, "flb_grace": 4},
    ],
    ids=["inside flb", "next to flb"],
)
def test_misspelled_flb_grace_is_a_deprecated_alias(section: dict[str, Any]) -> None:
    config = parse_destination_server(section)
    assert config.node.flb.grace == 4.0
    assert any("flb_grace is a deprecated spelling of destination_server.flb.grace" in w for w in config.warnings)


def test_grace_wins_over_flb_grace() -> None:
    config = parse_destination_server({**stdout_section(), "flb": {"grace": 2, "flb_grace": 4}})
    assert config.node.flb.grace == 2.0
    assert any("ignored" in w for w in config.warnings)


def test_seed_metrics_key_means_http_server() -> None:
    config = parse_destination_server({**stdout_section(), "flb": {"metrics": True}})
    assert config.node.flb.http_server is True
    assert any("flb.metrics" in w for w in config.warnings)


def test_unlisted_destination_section_is_ignored_with_a_warning() -> None:
    section = {**stdout_section(), "flb_minio": {"plugin": "dc_destinations/FlbMinIO", "inputs": ["/x"]}}
    config = parse_destination_server(section)
    assert config.names == ["flb_stdout"]
    assert config.warnings == [
        "destination_server.flb_minio: destination section not listed in destination_plugins, ignored"
    ]


def test_original_fluent_bit_input_keys_are_accepted_with_a_warning() -> None:
    config = parse_destination_server({**stdout_section(), "ros2_plugin_spin_time_ms": 100})
    assert any("ros2_plugin_spin_time_ms has no effect" in w for w in config.warnings)


def test_the_seed_tb3_demos_custom_str_params_in_destination_server_are_ignored_with_a_warning() -> None:
    section = {
        **stdout_section(),
        "custom_str_params_list": ["robot_name"],
        "custom_str_params": {"robot_name": {"name": "robot_name", "value": "C3PO"}},
    }
    config = parse_destination_server(section)
    assert config.names == ["flb_stdout"]
    assert config.warnings == [
        f"destination_server.{key}: ignored, it is a measurement_server parameter (its records carry them)"
        for key in ("custom_str_params_list", "custom_str_params")
    ]


def test_no_destination_is_valid_but_warned() -> None:
    config = parse_destination_server({})
    assert config.destinations == []
    assert config.inputs == set()
    assert any("destination_plugins is empty" in w for w in config.warnings)


def test_seed_uptime_demo_destination_section(tmp_path: Path) -> None:
    # The seed's "Uptime to stdout" demo, indentation restored, read through the parameter-file loader.
    text = """
destination_server:
  ros__parameters:
    flb:
      flush: 1
      flb_grace: 1
      log_level: "info"
      storage_path: "/var/log/flb-storage/"
      storage_sync: "full"
      storage_checksum: "off"
      storage_backlog_mem_limit: "1M"
      scheduler_cap: 200
      scheduler_base: 5
      http_server: true
      http_listen: "0.0.0.0"
      http_port: 2020
      in_storage_type: "filesystem"
      in_storage_pause_on_chunks_overlimit: "off"
    destination_plugins: ["flb_stdout"]
    flb_stdout:
      plugin: "dc_destinations/FlbStdout"
      inputs: ["/dc/measurement/uptime"]
      time_format: "double"
      time_key: "date"
      debug: false
"""
    params = tmp_path / "params.yaml"
    params.write_text(text)
    assert yaml.safe_load(text)  # the fixture itself is valid YAML
    config = parse_destination_server(load_params_file(params)["destination_server"])
    assert config.names == ["flb_stdout"]
    assert (config.node.flb.grace, config.node.flb.scheduler_cap, config.node.flb.storage_sync) == (
        1.0,
        200.0,
        "full",
    )


def test_dotted_keys_of_ros_parameter_files(tmp_path: Path) -> None:
    params = tmp_path / "params.yaml"
    params.write_text(
        "destination_server:\n  ros__parameters:\n    flb.flush: 2\n    destination_plugins: [n]\n"
        "    n.plugin: dc_destinations/Null\n    n.inputs: [/a]\n"
    )
    config = parse_destination_server(load_params_file(params)["destination_server"])
    assert config.node.flb.flush == 2.0
    assert config.destinations[0].plugin_class is Null


NO_EFFECT = "accepted for the original's files, has no effect because"


@pytest.mark.parametrize(
    ("section", "path"),
    [
        (
            {**stdout_section(), "flb": {"flush": 1, "storage_checksum": "on"}},
            "destination_server.flb.storage_checksum",
        ),
        (
            {
                "destination_plugins": ["pg"],
                "pg": {"plugin": "dc_destinations/PgSQL", "inputs": [UPTIME], "async": True},
            },
            "destination_server.pg.async",
        ),
        (
            {
                "destination_plugins": ["fm"],
                "fm": {
                    "plugin": "dc_destinations/FilesMetrics",
                    "inputs": [UPTIME],
                    "file_storage": ["minio"],
                    "minio": {"src_fields": ["local_paths.pgm"], "upload_fields": ["remote_paths.pgm"]},
                    "pgsql": {"time_key": "date"},
                },
            },
            "destination_server.fm.pgsql.time_key",
        ),
        (
            {
                "destination_plugins": ["tcp"],
                "tcp": {"plugin": "dc_destinations/TCP", "inputs": [UPTIME], "tls": {"active": "on", "debug": 2}},
            },
            "destination_server.tcp.tls.debug",
        ),
    ],
    ids=["server flb section", "plugin key by its alias", "nested section", "the tls section an alias holds"],
)
def test_a_compatibility_key_without_effect_is_said_once(section: dict[str, Any], path: str) -> None:
    warnings = parse_destination_server(section).warnings
    said = [w for w in warnings if NO_EFFECT in w]
    assert len(said) == 1 and said[0].startswith(f"{path}: {NO_EFFECT} "), warnings


def test_a_compatibility_key_left_out_is_not_mentioned() -> None:
    section = {"destination_plugins": ["pg"], "pg": {"plugin": "dc_destinations/PgSQL", "inputs": [UPTIME]}}
    assert parse_destination_server(section).warnings == []
