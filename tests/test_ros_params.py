"""Parameter files read as rcl reads them, ``--ros-args`` parameters over them, DC's settings as ROS parameters."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from dc_bringup.validate import validate_params_file
from dc_core.config import load_params, node_name_matches
from dc_core.declared_params import SECRET_SHOWN_AS, flatten, ros_value
from dc_core.errors import ConfigError
from dc_core.ros_args import check_ros_args, namespace_remap, param_sections, split_ros_args

# (what a file is, its text, the namespace dc-bringup runs in, measurement_server's parameters or None
# when the file runs no measurement_server there)
M = "measurement_server"
FILES: list[tuple[str, str, str, dict[str, Any] | None]] = [
    ("DC's own form", f"{M}:\n  ros__parameters:\n    a: 1\n", "", {"a": 1}),
    ("DC's own form under a namespace", f"{M}:\n  ros__parameters:\n    a: 1\n", "r1", {"a": 1}),
    ("fully qualified, root", f"/{M}:\n  ros__parameters:\n    a: 1\n", "", {"a": 1}),
    ("fully qualified root name, another namespace", f"/{M}:\n  ros__parameters:\n    a: 1\n", "r1", None),
    ("any namespace", f"/**/{M}:\n  ros__parameters:\n    a: 1\n", "", {"a": 1}),
    ("any namespace, nested one", f"/**/{M}:\n  ros__parameters:\n    a: 1\n", "r1/arm", {"a": 1}),
    ("one namespace token", f"/*/{M}:\n  ros__parameters:\n    a: 1\n", "r1", {"a": 1}),
    ("one namespace token, root", f"/*/{M}:\n  ros__parameters:\n    a: 1\n", "", None),
    ("namespace root key", f"/r1:\n  {M}:\n    ros__parameters:\n      a: 1\n", "r1", {"a": 1}),
    ("namespace root key without slash", f"r1:\n  {M}:\n    ros__parameters:\n      a: 1\n", "r1", {"a": 1}),
    ("namespace key, other namespace", f"r1:\n  {M}:\n    ros__parameters:\n      a: 1\n", "r2", None),
    ("namespace key, root", f"r1:\n  {M}:\n    ros__parameters:\n      a: 1\n", "", None),
    ("namespace path", f"/r1/{M}:\n  ros__parameters:\n    a: 1\n", "/r1/", {"a": 1}),
    ("nested namespaces", f"r1:\n  arm:\n    {M}:\n      ros__parameters:\n        a: 1\n", "r1/arm", {"a": 1}),
    (
        "/** adds use_sim_time, starts nothing",
        f"/**:\n  ros__parameters:\n    use_sim_time: true\n{M}:\n  ros__parameters:\n    a: 1\n",
        "",
        {"use_sim_time": True, "a": 1},
    ),
    (
        "/* adds to root nodes only",
        f"/*:\n  ros__parameters:\n    b: 2\n/**/{M}:\n  ros__parameters:\n    a: 1\n",
        "r1",
        {"a": 1},
    ),
    (
        "later section wins",
        f"{M}:\n  ros__parameters:\n    a: 1\n    flb: {{x: 1, y: 1}}\n/**:\n  ros__parameters:\n    a: 2\n    flb.y: 2\n",
        "",
        {"a": 2, "flb": {"x": 1, "y": 2}},
    ),
    (
        "earlier section loses",
        f"/**:\n  ros__parameters:\n    a: 2\n{M}:\n  ros__parameters:\n    a: 1\n",
        "",
        {"a": 1},
    ),
    (
        # rcl keys a node name once, at its first appearance: the second /r1/measurement_server section
        # updates the first, which /** still follows.
        "a name written twice keeps its first place",
        f"/r1/{M}:\n  ros__parameters:\n    a: 1\n/**:\n  ros__parameters:\n    a: 2\n"
        f"r1:\n  {M}:\n    ros__parameters:\n      a: 3\n",
        "r1",
        {"a": 2},
    ),
    (
        "another robot's section beside this one's",
        f"/r2/{M}:\n  ros__parameters:\n    a: 2\n/r1/{M}:\n  ros__parameters:\n    a: 1\n",
        "r1",
        {"a": 1},
    ),
]


@pytest.mark.parametrize(("what", "text", "namespace", "expected"), FILES, ids=[f[0] for f in FILES])
def test_sections_apply_as_rcl_applies_them(
    tmp_path: Path, what: str, text: str, namespace: str, expected: dict[str, Any] | None
) -> None:
    params = tmp_path / "params.yaml"
    # A destination_server in every namespace: the file runs something, whatever the case.
    params.write_text(text + "/**/destination_server:\n  ros__parameters:\n    c: 3\n")
    loaded = load_params(params, namespace)
    assert loaded.servers.get(M) == expected
    assert loaded.servers["destination_server"]["c"] == 3


@pytest.mark.parametrize(
    ("pattern", "fqn", "matches"),
    [
        ("/**", "/n", True),
        ("/**", "/a/b/n", True),
        ("/*", "/n", True),
        ("/*", "/a/n", False),
        ("/**/n", "/n", True),
        ("/**/n", "/a/b/n", True),
        ("/*/n", "/n", False),
        ("/*/n", "/a/n", True),
        ("/a/*", "/a/n", True),
        ("/a/*", "/b/n", False),
        ("/a/n", "/a/n", True),
        ("/n", "/a/n", False),
        ("n", "/a/n", True),  # DC's own bare form: the server of that name wherever it runs
        ("/a.b/n", "/axb/n", False),  # only * is special
    ],
)
def test_node_name_wildcards(pattern: str, fqn: str, matches: bool) -> None:
    assert node_name_matches(pattern, fqn) is matches


def test_sections_for_nodes_dc_does_not_run_are_listed_once(tmp_path: Path) -> None:
    params = tmp_path / "params.yaml"
    params.write_text(
        "controller_server:\n  ros__parameters:\n    controller_frequency: 20.0\n"
        f"/r2/{M}:\n  ros__parameters:\n    a: 2\n/r1/{M}:\n  ros__parameters:\n    measurement_plugins: []\n"
        "/**:\n  ros__parameters:\n    use_sim_time: false\n"
    )
    report = validate_params_file(params, "r1")
    assert report.servers == [M]
    assert report.notes == [
        "sections for nodes DC does not run, ignored (other nodes' parameters): controller_server, /r2/measurement_server"
    ]
    assert not any("controller_server" in w for w in report.warnings)


@pytest.mark.parametrize(
    ("text", "namespace", "path", "message"),
    [
        ("/r1/measurement_sever:\n  ros__parameters: {}\n", "r1", "r1/measurement_sever", "did you mean"),
        (f"r1:\n  {M}:\n    a: 1\n", "r1", f"r1/{M}", "expected a 'ros__parameters' mapping"),
        (f"/r1/{M}:\n  ros__parameters:\n    a: 1\n", "r2", "", "no DC server section for nodes in namespace /r2"),
    ],
)
def test_file_errors(tmp_path: Path, text: str, namespace: str, path: str, message: str) -> None:
    params = tmp_path / "params.yaml"
    params.write_text(text)
    with pytest.raises(ConfigError, match=message) as caught:
        load_params(params, namespace)
    assert caught.value.path == path


# -- --ros-args -------------------------------------------------------------------------------------


def test_split_ros_args() -> None:
    argv = ["p.yaml", "--namespace", "r1", "--ros-args", "-r", "/tf:=tf", "-p", "a:=1", "--", "--single-process"]
    assert split_ros_args(argv) == (
        ["p.yaml", "--namespace", "r1", "--single-process"],
        ["-r", "/tf:=tf", "-p", "a:=1"],
    )
    assert split_ros_args(["p.yaml"]) == (["p.yaml"], [])


@pytest.mark.parametrize(
    ("ros_args", "message"),
    [
        (["--frobnicate"], "unknown ROS argument '--frobnicate'"),
        (["-p"], "-p needs a value"),
        (["-r", "/tf"], "expected NAME:=VALUE"),
    ],
)
def test_bad_ros_args(ros_args: list[str], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        check_ros_args(ros_args)


def test_ros_args_parameters_win_over_the_file_in_command_line_order(tmp_path: Path) -> None:
    params = tmp_path / "params.yaml"
    params.write_text(f"{M}:\n  ros__parameters:\n    a: 1\n    b: 1\n    flb: {{x: 1, y: 1}}\n")
    extra = tmp_path / "extra.yaml"
    # rcl's reading: a bare name is the root namespace's node, wildcards apply everywhere.
    extra.write_text(f"/**:\n  ros__parameters:\n    b: 2\n    flb.x: 2\n/r1/{M}:\n  ros__parameters:\n    c: 2\n")
    ros_args = ["-p", "a:=3", "--params-file", str(extra), "-p", f"{M}:flb.y:=[1, 2]", "-p", "b:=3"]
    assert load_params(params, "", param_sections(ros_args)).servers[M] == {
        "a": 3,
        "b": 3,
        "flb": {"x": 2, "y": [1, 2]},
    }
    # Under /r1 the node-scoped -p (written for /measurement_server) is not this node's.
    assert load_params(params, "r1", param_sections(ros_args)).servers[M] == {
        "a": 3,
        "b": 3,
        "flb": {"x": 2, "y": 1},
        "c": 2,
    }


def test_a_wrong_type_given_with_p_is_reported_with_its_yaml_path(tmp_path: Path) -> None:
    params = tmp_path / "params.yaml"
    params.write_text(f"{M}:\n  ros__parameters:\n    measurement_plugins: []\n")
    with pytest.raises(ConfigError) as caught:
        validate_params_file(params, "", ["-p", f"{M}:heartbeat_period:=fast"])
    assert caught.value.path == f"{M}.heartbeat_period"


def test_namespace_remap() -> None:
    assert namespace_remap(["-r", "/tf:=tf", "-r", "__ns:=/r1"]) == "/r1"
    assert namespace_remap(["-r", "/tf:=tf"]) is None
    assert namespace_remap(["--frobnicate"]) is None  # check_ros_args says what is wrong


# -- DC's settings as ROS parameters ---------------------------------------------------------------


def test_flattened_parameters_hide_secrets() -> None:
    flat = flatten(
        {
            "pg": {"password": "hunter2", "host": "db", "port": 5432},
            "mqtt": {"brokers": [{"host": "a", "password": "x"}]},
            "flb": {},
            "empty_password": "",
        }
    )
    assert flat == {
        "pg.password": SECRET_SHOWN_AS,
        "pg.host": "db",
        "pg.port": 5432,
        "mqtt.brokers": [{"host": "a", "password": SECRET_SHOWN_AS}],
        "empty_password": "",
    }


@pytest.mark.parametrize(
    ("value", "held", "as_json"),
    [
        (True, True, False),
        (3, 3, False),
        (2.5, 2.5, False),
        ("x", "x", False),
        (["a", "b"], ["a", "b"], False),
        ([1, 2], [1, 2], False),
        ([1, 2.5], [1.0, 2.5], False),
        ([True, False], [True, False], False),
        ([], "[]", True),
        (None, "null", True),
        ([1, "a"], '[1, "a"]', True),
        ([{"a": 1}], '[{"a": 1}]', True),
        (2**70, str(2**70), True),
    ],
)
def test_ros_values(value: Any, held: Any, as_json: bool) -> None:
    assert ros_value(value) == (held, as_json)


def test_a_wildcard_sets_on_each_server_only_the_parameters_it_has(tmp_path: Path) -> None:
    params = tmp_path / "params.yaml"
    params.write_text(
        f"{M}:\n  ros__parameters:\n    uptime: {{plugin: u}}\n"
        "destination_server:\n  ros__parameters:\n    flb: {flush: 1}\n"
        "/**:\n  ros__parameters:\n    flb.grace: 5\n    unknown_to_all: 1\n"
    )
    ros_args = ["-p", "uptime.polling_interval:=5000", "-p", "heartbeat_period:=0.5"]
    servers = load_params(params, "", param_sections(ros_args)).servers
    # As a ROS node ignores overrides of parameters it does not declare: destination_server has no
    # uptime, measurement_server no flb; heartbeat_period is every server's.
    assert servers[M] == {"uptime": {"plugin": "u", "polling_interval": 5000}, "heartbeat_period": 0.5}
    assert servers["destination_server"] == {"flb": {"flush": 1, "grace": 5}, "heartbeat_period": 0.5}
