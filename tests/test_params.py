"""Typed parameters: defaults, types, ranges, unknown keys, paths in messages (dc_core/params.py)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import pytest

from dc_core.config import load_params_file, nest_dotted_keys
from dc_core.errors import ConfigError
from dc_core.params import describe_params, host_problem, param, parse_params, port_problem


@dataclass(frozen=True, kw_only=True)
class Inner:
    enabled: bool = param(True, doc="on")


@dataclass(frozen=True, kw_only=True)
class Example:
    name: str = param(doc="required name")
    interval: int = param(1000, minimum=100, doc="ms")
    ratio: float = param(0.5, doc="a number")
    mode: str = param("a", choices=("a", "b"), doc="mode")
    tags: list[str] = param([], doc="tags")
    password: str = param("", secret=True, doc="secret")
    inner: Inner = param(default_factory=Inner, doc="nested")
    grace: float = param(1.0, aliases=("old_grace",), doc="aliased")


def test_defaults_and_values() -> None:
    p = parse_params(Example, {"name": "x", "ratio": 2, "tags": ["a"]}, "server.plugin")
    assert p.name == "x" and p.interval == 1000 and p.ratio == 2.0 and isinstance(p.ratio, float)
    assert p.tags == ["a"] and p.inner.enabled is True


def test_list_defaults_are_not_shared() -> None:
    a = parse_params(Example, {"name": "x"}, "s")
    b = parse_params(Example, {"name": "y"}, "s")
    assert a.tags is not b.tags


@pytest.mark.parametrize(
    ("values", "message"),
    [
        ({"name": "x", "interval": "fast"}, 'server.plugin.interval: expected an integer, got "fast"'),
        ({"name": "x", "interval": 10}, "server.plugin.interval: expected an integer >= 100, got 10"),
        ({"name": "x", "interval": True}, "server.plugin.interval: expected an integer, got True"),
        ({"name": "x", "mode": "c"}, 'server.plugin.mode: expected one of "a", "b", got "c"'),
        ({"name": "x", "tags": "a"}, 'server.plugin.tags: expected a list of string, got "a"'),
        ({"name": "x", "tags": [1, {"a": 1}]}, "server.plugin.tags[1]: expected a string"),
        ({}, "server.plugin.name: required parameter missing (expected string)"),
        ({"name": "x", "intervall": 100}, 'server.plugin.intervall: unknown parameter (did you mean "interval"?)'),
        ({"name": "x", "inner": {"enabled": "maybe"}}, 'server.plugin.inner.enabled: expected a boolean, got "maybe"'),
    ],
)
def test_errors_name_the_yaml_path(values: dict[str, object], message: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_params(Example, values, "server.plugin")
    assert str(info.value).startswith(message)


def test_bool_words_and_aliases() -> None:
    p = parse_params(Example, {"name": "x", "inner": {"enabled": "off"}, "old_grace": 3}, "s")
    assert p.inner.enabled is False and p.grace == 3.0


def test_ignore_lets_other_owners_keep_their_keys() -> None:
    p = parse_params(Example, {"name": "x", "plugin": "y"}, "s", ignore={"plugin"})
    assert p.name == "x"


def test_describe_and_secrets_stay_out_of_repr() -> None:
    described = {p.name: p for p in describe_params(Example)}
    assert described["name"].required and described["interval"].default == 1000
    assert described["inner.enabled"].type_name == "boolean"
    shown = repr(parse_params(Example, {"name": "x", "password": "hunter2"}, "s"))
    assert "hunter2" not in shown and "password" not in shown and "name='x'" in shown


def test_dotted_keys_equal_nested_sections() -> None:
    assert nest_dotted_keys({"flb.flush": 1, "flb": {"grace": 2}, "a": 3}) == {"flb": {"flush": 1, "grace": 2}, "a": 3}


def test_load_params_file_errors(tmp_path: object) -> None:
    from pathlib import Path

    folder = Path(str(tmp_path))
    bad = folder / "bad.yaml"
    bad.write_text("measurement_server:\n  ros__parameters:\n    a: [1, 2\n")
    with pytest.raises(ConfigError, match="invalid YAML at line"):
        load_params_file(bad)
    with pytest.raises(ConfigError, match="cannot read parameter file"):
        load_params_file(folder / "missing.yaml")
    other = folder / "other.yaml"
    other.write_text("some_node:\n  ros__parameters:\n    a: 1\n")
    with pytest.raises(ConfigError, match="no DC server section"):
        load_params_file(other)
    no_ros = folder / "noros.yaml"
    no_ros.write_text("measurement_server:\n  a: 1\n")
    with pytest.raises(ConfigError, match="measurement_server: expected a 'ros__parameters' mapping"):
        load_params_file(no_ros)


# -- use_sim_time: a ROS parameter every server takes in its section ---------------------------------


def _server_sections() -> list[tuple[str, Any, dict[str, Any]]]:
    from dc_destinations.config import parse_destination_server
    from dc_group.config import parse_group_server
    from dc_measurements.config import parse_measurement_server

    return [
        ("measurement_server", parse_measurement_server, {"measurement_plugins": []}),
        ("destination_server", parse_destination_server, {"destination_plugins": []}),
        ("group_server", parse_group_server, {"groups": []}),
    ]


@pytest.mark.parametrize("server", ["measurement_server", "destination_server", "group_server"])
def test_every_server_takes_use_sim_time(server: str) -> None:
    name, parse, section = next(s for s in _server_sections() if s[0] == server)
    assert parse(section).node.use_sim_time is False
    assert parse({**section, "use_sim_time": True}).node.use_sim_time is True
    with pytest.raises(ConfigError, match=f"{name}.use_sim_time"):
        parse({**section, "use_sim_time": "sometimes"})


def test_environment_references_are_replaced_in_every_string(tmp_path: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("DC_TEST_PASSWORD", "s3cr3t")
    monkeypatch.setenv("DC_TEST_HOST", "db.local")
    monkeypatch.setenv("DC_TEST_PORT", "15432")
    monkeypatch.setenv("DC_TEST_PIN", "0123")
    file = tmp_path / "params.yaml"
    file.write_text(
        "destination_server:\n  ros__parameters:\n"
        "    pg: {password: '${DC_TEST_PASSWORD}', host: 'x-${DC_TEST_HOST}', hosts: ['${DC_TEST_HOST}']}\n"
        "    db: {port: '${DC_TEST_PORT}', pin: '${DC_TEST_PIN}', where: ':${DC_TEST_PORT}'}\n"
        "    s3: {s3_key_format: '/logs/$TAG/%Y', path: '$HOME/data', literal: '$${DC_TEST_HOST}'}\n"
    )
    params = load_params_file(file)["destination_server"]
    assert params["pg"] == {"password": "s3cr3t", "host": "x-db.local", "hosts": ["db.local"]}
    # A value that is one reference to an integer is an integer (a port); "0123" stays text (a PIN).
    assert params["db"] == {"port": 15432, "pin": "0123", "where": ":15432"}
    # Without braces a $ keeps its own meaning (S3's $TAG, paths' $HOME expanded later); $${ is a literal ${.
    assert params["s3"] == {"s3_key_format": "/logs/$TAG/%Y", "path": "$HOME/data", "literal": "${DC_TEST_HOST}"}


def test_an_unset_environment_reference_names_the_key(tmp_path: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("DC_TEST_UNSET", raising=False)
    file = tmp_path / "params.yaml"
    file.write_text("destination_server:\n  ros__parameters:\n    pg.password: '${DC_TEST_UNSET}'\n")
    with pytest.raises(ConfigError) as caught:
        load_params_file(file)
    assert caught.value.path == "destination_server.pg.password"
    assert "environment variable DC_TEST_UNSET is not set" in str(caught.value)


@pytest.mark.parametrize(
    ("port", "ok"), [(1, True), (65535, True), ("5432", True), (0, False), (65536, False), ("x", False)]
)
def test_port_problem_is_the_one_port_check(port: int | str, ok: bool) -> None:
    assert (port_problem(port) is None) == ok
    if not ok:
        assert port_problem(port) == "a TCP port from 1 to 65535"


@pytest.mark.parametrize(
    ("host", "ok"),
    [("127.0.0.1", True), ("::1", True), ("db.example.org", True), ("", False), ("http://x", False), ("a b", False)],
)
def test_host_problem_refuses_what_is_not_a_host(host: str, ok: bool) -> None:
    assert (host_problem(host) is None) == ok
