"""Topic names as DC resolves them: rclpy's expansion, and every section's names in the servers' namespace."""

from __future__ import annotations

import pytest
from rclpy.expand_topic_name import expand_topic_name

from dc_core.errors import ConfigError
from dc_core.handoff import destination_inputs
from dc_core.topics import published_topics, resolve_topic
from dc_destinations.config import parse_destination_server
from dc_destinations.server import internal_prefixes
from dc_group.config import parse_group_server
from dc_measurements.config import parse_measurement_server

NAMES = ["dc/measurement/a", "/dc/measurement/a", "~/private", "~", "{node}/x", "a/{ns}", "b/{namespace}/c"]


@pytest.mark.parametrize("namespace", ["/", "/r1", "/fleet/r2"])
@pytest.mark.parametrize("name", NAMES)
def test_names_resolve_as_rclpy_expands_them(name: str, namespace: str) -> None:
    assert resolve_topic(name, namespace, "measurement_server") == expand_topic_name(
        name, "measurement_server", namespace
    )


def test_namespace_spellings_are_one() -> None:
    assert {resolve_topic("dc/heartbeat", ns) for ns in ("r1", "/r1", "/r1/", "r1/")} == {"/r1/dc/heartbeat"}
    assert {resolve_topic("dc/heartbeat", ns) for ns in ("", "/")} == {"/dc/heartbeat"}


MEASUREMENTS = {
    "measurement_plugins": ["uptime", "cpu"],
    "uptime": {"plugin": "dc_measurements/Uptime"},
    "cpu": {"plugin": "dc_measurements/Cpu", "topic_output": "/dc/measurement/cpu"},
}
GROUPS = {"groups": ["g"], "g": {"inputs": ["dc/measurement/uptime", "/dc/measurement/cpu"]}}
DESTINATIONS = {
    "destination_plugins": ["out"],
    "out": {"plugin": "dc_destinations/Stdout", "inputs": ["dc/group/g", "/dc/measurement/cpu", "plain"]},
}


def test_without_a_namespace_the_defaults_are_the_absolute_names_of_before() -> None:
    measurements = parse_measurement_server(MEASUREMENTS)
    assert [m.output_topic for m in measurements.measurements] == ["/dc/measurement/uptime", "/dc/measurement/cpu"]
    group = parse_group_server(GROUPS).groups[0]
    assert (group.inputs, group.output) == (("/dc/measurement/uptime", "/dc/measurement/cpu"), "/dc/group/g")
    (out,) = parse_destination_server(DESTINATIONS).destinations
    assert out.common.inputs == ["/dc/group/g", "/dc/measurement/cpu", "/plain"]


def test_in_a_namespace_relative_and_default_names_follow_it_and_absolute_ones_stay() -> None:
    measurements = parse_measurement_server(MEASUREMENTS, namespace="/r1")
    assert [m.output_topic for m in measurements.measurements] == ["/r1/dc/measurement/uptime", "/dc/measurement/cpu"]
    assert published_topics({"measurement_server": MEASUREMENTS}, "/r1")[0].keys() == {
        "/r1/dc/measurement/uptime",
        "/dc/measurement/cpu",
    }
    group = parse_group_server(GROUPS, namespace="/r1").groups[0]
    assert (group.inputs, group.output) == (("/r1/dc/measurement/uptime", "/dc/measurement/cpu"), "/r1/dc/group/g")
    (out,) = parse_destination_server(DESTINATIONS, namespace="/r1").destinations
    assert out.common.inputs == ["/r1/dc/group/g", "/dc/measurement/cpu", "/r1/plain"]
    # The measurement and group servers compare their outputs with what the destination reads.
    servers = {"destination_server": {"ros__parameters": DESTINATIONS}}
    assert destination_inputs(servers, "/r1") == {"/r1/dc/group/g", "/dc/measurement/cpu", "/r1/plain"}
    assert destination_inputs(servers) == {"/dc/group/g", "/dc/measurement/cpu", "/plain"}
    # Records on the namespace's DC topics and on the root's are guarded alike (trust_tags_from).
    assert internal_prefixes("/r1") == ("/r1/dc/measurement/", "/r1/dc/group/", "/dc/measurement/", "/dc/group/")
    assert internal_prefixes("/") == ("/dc/measurement/", "/dc/group/")


def test_one_topic_written_relative_and_absolute_is_one_input() -> None:
    twice = {"groups": ["g"], "g": {"inputs": ["dc/measurement/a", "/dc/measurement/a"]}}
    with pytest.raises(ConfigError, match=r"group_server.g.inputs\[1\].*/dc/measurement/a is listed twice"):
        parse_group_server(twice)
    assert parse_group_server(twice, namespace="/r1").groups[0].inputs == ("/r1/dc/measurement/a", "/dc/measurement/a")
