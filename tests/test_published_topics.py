"""The topics destination_server takes as DC's own, read from the other servers' sections by
dc_core.topics.published_topics, without their configuration classes (issue 25, item 6)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from dc_bringup.validate import validate_params_file
from dc_core.config import load_params_file
from dc_core.qos import RECORD_HISTORY_DEPTH
from dc_core.topics import group_topic, measurement_topic, published_topics
from dc_group.config import parse_group_server
from dc_measurements.config import parse_measurement_server

REPO = Path(__file__).resolve().parent.parent
PARAMS = sorted((REPO / "params").rglob("*.yaml"))


@pytest.mark.parametrize("namespace", ["/", "/r1"])
@pytest.mark.parametrize("path", PARAMS, ids=lambda p: str(p.relative_to(REPO)))
def test_the_topics_read_are_those_the_servers_configurations_publish(
    path: Path, namespace: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The few keys read here agree with the servers' own parsers on every parameter file shipped,
    at the root and in a namespace (dc-bringup --namespace r1)."""
    for name in re.findall(r"\$\{(\w+)\}", path.read_text()):  # the demos' servers.env
        monkeypatch.setenv(name, "5432" if name.endswith("PORT") else "127.0.0.1")
    configs = validate_params_file(path, namespace).configs
    expected: dict[str, int] = {}
    if "measurement_server" in configs:
        expected |= {m.output_topic: m.common.history_depth for m in configs["measurement_server"].measurements}
    if "group_server" in configs:
        expected |= dict.fromkeys(configs["group_server"].outputs, RECORD_HISTORY_DEPTH)
    assert published_topics(load_params_file(path, namespace), namespace) == (expected, [])


def test_defaults_and_given_names_with_their_depths() -> None:
    servers = {
        "measurement_server": {
            "measurement_plugins": ["cpu", "map"],
            "cpu": {"plugin": "dc_measurements/Cpu"},
            "map": {"plugin": "dc_measurements/Map", "topic_output": "/maps", "history_depth": 3},
        },
        "group_server": {"groups": ["robot", "both"], "robot": {"inputs": ["/a"]}, "both": {"output": "/b"}},
    }
    assert published_topics(servers) == (
        {
            "/dc/measurement/cpu": RECORD_HISTORY_DEPTH,
            "/maps": 3,
            "/dc/group/robot": RECORD_HISTORY_DEPTH,
            "/b": RECORD_HISTORY_DEPTH,
        },
        [],
    )
    # The defaults are relative (issue 31 item 2): at the root they are the absolute names of before.
    assert measurement_topic("cpu") == "dc/measurement/cpu" and group_topic("robot") == "dc/group/robot"


def test_in_a_namespace_defaults_and_relative_names_follow_it_absolute_ones_stay() -> None:
    """Each name resolved for the node that publishes it, as the measurement and group servers in
    namespace /r1 resolve it (issue 31 item 2): the destination server there takes the same as DC's own."""
    measurements = {
        "measurement_plugins": ["cpu", "map", "own", "private"],
        "cpu": {"plugin": "dc_measurements/Cpu"},
        "map": {"plugin": "dc_measurements/Cpu", "topic_output": "/maps", "history_depth": 3},
        "own": {"plugin": "dc_measurements/Cpu", "topic_output": "robot/own"},
        "private": {"plugin": "dc_measurements/Cpu", "topic_output": "~/private"},
    }
    groups = {
        "groups": ["robot", "both", "mine"],
        "robot": {"inputs": ["dc/measurement/cpu"]},
        "both": {"inputs": ["/maps"], "output": "/b"},
        "mine": {"inputs": ["robot/own"], "output": "{node}/mine"},
    }
    topics, problems = published_topics({"measurement_server": measurements, "group_server": groups}, "r1")
    assert (topics, problems) == (
        {
            "/r1/dc/measurement/cpu": RECORD_HISTORY_DEPTH,
            "/maps": 3,
            "/r1/robot/own": RECORD_HISTORY_DEPTH,
            "/r1/measurement_server/private": RECORD_HISTORY_DEPTH,
            "/r1/dc/group/robot": RECORD_HISTORY_DEPTH,
            "/b": RECORD_HISTORY_DEPTH,
            "/r1/group_server/mine": RECORD_HISTORY_DEPTH,
        },
        [],
    )
    parsed = {
        m.output_topic: m.common.history_depth
        for m in parse_measurement_server(measurements, namespace="/r1").measurements
    }
    parsed |= dict.fromkeys(parse_group_server(groups, namespace="/r1").outputs, RECORD_HISTORY_DEPTH)
    assert topics == parsed


def test_what_does_not_read_is_said_with_its_path_and_the_rest_is_still_known() -> None:
    servers = {
        "measurement_server": {
            "measurement_plugins": ["cpu", "missing", "odd", "shallow"],
            "cpu": {},
            "odd": {"topic_output": 5},
            "shallow": {"history_depth": 0},
        },
        "group_server": {"groups": "robot"},
    }
    topics, problems = published_topics(servers)
    assert topics == {"/dc/measurement/cpu": RECORD_HISTORY_DEPTH}
    assert [p.partition(":")[0] for p in problems] == [
        "measurement_server.missing",
        "measurement_server.odd.topic_output",
        "measurement_server.shallow.history_depth",
        "group_server.groups",
    ]
    assert published_topics({"destination_server": {}}) == ({}, [])
