"""Group configuration, output record building and the per-group pipeline, without ROS."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from dc_core.config import load_params_file
from dc_core.errors import ConfigError
from dc_core.records import MalformedRecord
from dc_core.testing import RecordingLogger
from dc_group.config import GroupConfig, parse_group_server
from dc_group.merge import (
    InputRecord,
    exclude,
    flatten_dotted,
    merge,
    parse_input,
    record_key,
)
from dc_group.pipeline import GroupPipeline

REPO = Path(__file__).resolve().parent.parent
S = 1_000_000_000


def group(section: dict[str, Any], name: str = "g") -> GroupConfig:
    return parse_group_server({"groups": [name], name: section}).groups[0]


def rec(key: str, record: dict[str, Any], topic: str | None = None) -> InputRecord:
    return InputRecord(topic=topic or f"/dc/measurement/{key}", key=key, record=record)


# -- configuration ---------------------------------------------------------------------------
def test_defaults() -> None:
    g = group({"inputs": ["/dc/measurement/memory", "/dc/measurement/uptime"]}, "memory_uptime")
    assert g.output == "/dc/group/memory_uptime"
    assert g.sync_delay == 5.0
    assert g.sync_timeout == 6.0  # sync_delay + 1 s
    assert g.emit_partial is False
    assert g.queue_size == 10
    assert g.group_key == "memory_uptime"
    assert g.exclude_keys == ()
    assert g.tags == ()
    assert g.nested_data is True
    assert g.include_group_name is True


def test_explicit_values() -> None:
    g = group(
        {
            "inputs": ["/a"],
            "output": "/out",
            "sync_delay": 1,
            "sync_timeout": 3.5,
            "on_sync_timeout": "emit_partial",
            "queue_size": 4,
            "group_key": "k",
            "exclude_keys": ["*.run_id"],
            "tags": ["flb_stdout"],
            "nested_data": False,
            "include_group_name": False,
        }
    )
    assert (g.output, g.sync_delay, g.sync_timeout, g.emit_partial, g.queue_size) == (
        "/out",
        1.0,
        3.5,
        True,
        4,
    )
    assert (g.group_key, g.exclude_keys, g.tags) == ("k", ("*.run_id",), ("flb_stdout",))
    assert (g.nested_data, g.include_group_name) == (False, False)


def test_inputs_outputs_and_tags_of_the_server() -> None:
    config = parse_group_server(
        {
            "groups": ["a", "b"],
            "a": {"inputs": ["/m/1", "/m/2"], "tags": ["x"]},
            "b": {"inputs": ["/dc/group/a", "/m/2"], "output": "/out/b", "tags": ["y", "z"]},
        }
    )
    assert config.inputs == {"/m/1", "/m/2", "/dc/group/a"}
    assert config.outputs == {"/dc/group/a", "/out/b"}
    assert config.tags == {"/dc/group/a": ["x"], "/out/b": ["y", "z"]}
    assert config.warnings == []


@pytest.mark.parametrize(
    ("section", "path", "message"),
    [
        ({}, "group_server.groups", "required parameter missing"),
        ({"groups": "g"}, "group_server.groups", "expected a list of string"),
        ({"groups": ["g"]}, "group_server.g", "group section missing"),
        ({"groups": ["g"], "g": {}}, "group_server.g.inputs", "required parameter missing"),
        ({"groups": ["g"], "g": {"inputs": []}}, "group_server.g.inputs", "at least one input"),
        ({"groups": ["g"], "g": {"inputs": ["/a", "/a"]}}, "group_server.g.inputs[1]", "listed twice"),
        ({"groups": ["g"], "g": {"inputs": ["/a"], "sync_delay": -1}}, "group_server.g.sync_delay", ">= 0"),
        ({"groups": ["g"], "g": {"inputs": ["/a"], "sync_timeout": 0}}, "group_server.g.sync_timeout", "> 0"),
        ({"groups": ["g"], "g": {"inputs": ["/a"], "on_sync_timeout": "wait"}},
         "group_server.g.on_sync_timeout", '"drop", "emit_partial"'),
        ({"groups": ["g"], "g": {"inputs": ["/a"], "queue_size": 0}}, "group_server.g.queue_size", ">= 1"),
        ({"groups": ["g"], "g": {"inputs": ["/a"], "sync_dalay": 1}}, "group_server.g.sync_dalay",
         'did you mean "sync_delay"'),
        ({"groups": ["g"], "g": {"inputs": ["/a"]}, "h": {"inputs": ["/b"]}}, "group_server.h",
         "not a group listed"),
        ({"groups": ["g", "g"], "g": {"inputs": ["/a"]}}, "group_server.groups[1]", "listed twice"),
        ({"groups": ["g"], "g": {"inputs": ["/a"], "exclude_keys": ["a..b"]}},
         "group_server.g.exclude_keys[0]", "paths"),
        ({"groups": ["g"], "g": {"inputs": ["/dc/group/g"]}}, "group_server.g.inputs", "loop: g -> g"),
        ({"groups": ["a", "b"], "a": {"inputs": ["/x"], "output": "/o"},
          "b": {"inputs": ["/y"], "output": "/o"}}, "group_server.b.output", "already the output of group a"),
        ({"groups": ["g"], "g": {"inputs": ["/a"]}, "http_port": "2021"}, "group_server.http_port", "integer"),
        ({"groups": ["g"], "g": {"inputs": ["/a"]}, "http_port": 70000}, "group_server.http_port", "<= 65535"),
        ({"groups": ["http_server"]}, "group_server.groups[0]", "is a server parameter"),
    ],
)  # fmt: skip
def test_configuration_errors_name_the_yaml_path(section: dict[str, Any], path: str, message: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_group_server(section)
    assert info.value.path == path
    assert message in info.value.message


def test_the_metrics_http_server_is_on_by_default_on_loopback() -> None:
    default = parse_group_server({"groups": ["g"], "g": {"inputs": ["/a"]}})
    assert (default.node.http_server, default.node.http_listen, default.node.http_port) == (True, "127.0.0.1", 2021)
    disabled = parse_group_server({"groups": ["g"], "g": {"inputs": ["/a"]}, "http_server": False, "http_port": 0})
    assert (disabled.node.http_server, disabled.node.http_port) == (False, 0)


def test_groups_feeding_each_other_in_a_loop_are_refused() -> None:
    with pytest.raises(ConfigError, match="loop"):
        parse_group_server(
            {
                "groups": ["a", "b", "c"],
                "a": {"inputs": ["/m", "/dc/group/c"]},
                "b": {"inputs": ["/dc/group/a"]},
                "c": {"inputs": ["/dc/group/b"]},
            }
        )


def test_a_timeout_shorter_than_the_slop_is_a_warning() -> None:
    config = parse_group_server({"groups": ["g"], "g": {"inputs": ["/a"], "sync_delay": 5, "sync_timeout": 2}})
    assert len(config.warnings) == 1
    assert "group_server.g" in config.warnings[0]


def test_use_sim_time_is_accepted() -> None:
    assert parse_group_server({"groups": ["g"], "g": {"inputs": ["/a"]}, "use_sim_time": False}).groups


@pytest.mark.parametrize(
    "file", ["params/examples/example_5_fixed.yaml", "params/demos/group_memory_uptime_stdout.yaml",
             "params/examples/group_of_groups.yaml"],
)  # fmt: skip
def test_shipped_configurations_parse(file: str) -> None:
    config = parse_group_server(load_params_file(REPO / file)["group_server"])
    assert config.groups


# -- output record ---------------------------------------------------------------------------
def test_record_key_falls_back_to_the_last_topic_segment() -> None:
    assert record_key("memory", "/dc/measurement/mem") == "memory"
    assert record_key("", "/dc/measurement/cpu") == "cpu"
    assert record_key("", "/robot/cpu/") == "cpu"


def test_parse_input() -> None:
    parsed = parse_input("/dc/measurement/cpu", "", '{"usage": 3, "tags": ["x"]}')
    assert parsed == InputRecord("/dc/measurement/cpu", "cpu", {"usage": 3, "tags": ["x"]})


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ("{not json", "invalid JSON"),
        ("[1, 2]", "expected a JSON object, got a JSON array"),
        ("", "invalid JSON"),
        ("null", "got a JSON null"),
        ('{"a": NaN}', "NaN is not a JSON number"),
        ('{"a": 1e400}', "not finite"),
        ('{"t": "\\udcff"}', "lone surrogate"),
        ('{"a": ' + "[" * 5000 + "]" * 5000 + "}", "nested too deeply"),
    ],
    ids=["not-json", "array", "empty", "null", "nan", "overflow", "lone-surrogate", "deep"],
)
def test_malformed_input_is_a_clear_error(data: str, message: str) -> None:
    with pytest.raises(MalformedRecord, match="/dc/measurement/cpu") as info:
        parse_input("/dc/measurement/cpu", "", data)
    assert message in str(info.value)


def test_merge_nests_records_removes_inner_tags_and_adds_the_group_metadata() -> None:
    g = group({"inputs": ["/dc/measurement/memory", "/dc/measurement/uptime"], "tags": ["flb_stdout"]},
              "memory_uptime")  # fmt: skip
    merged = merge(
        g,
        [
            rec("memory", {"used": 71.6, "tags": ["flb_stdout"], "run_id": "3"}),
            rec("uptime", {"time": 96894, "tags": ["flb_stdout"], "run_id": "3"}),
        ],
    )
    assert merged.record == {
        "memory": {"used": 71.6, "run_id": "3"},
        "uptime": {"time": 96894, "run_id": "3"},
        "tags": ["flb_stdout"],
        "name": "memory_uptime",
        "run_id": "3",
    }
    assert list(merged.record) == ["memory", "uptime", "tags", "name", "run_id"]
    assert merged.renamed == []


def test_a_group_record_carries_robot_name_and_run_id_at_the_top_level() -> None:
    # Where a query (and PgSQL's typed columns) looks for them in every record, even when the
    # group drops the members' copies.
    g = group({"inputs": ["/dc/measurement/a", "/dc/measurement/b"], "exclude_keys": ["*.run_id"]})
    merged = merge(g, [None, rec("b", {"v": 2, "robot_name": "r7", "run_id": "12"})])
    assert merged.record == {"b": {"v": 2, "robot_name": "r7"}, "missing_inputs": ["/dc/measurement/a"],
                             "name": "g", "robot_name": "r7", "run_id": "12"}  # fmt: skip
    flat = group({"inputs": ["/dc/measurement/a"], "nested_data": False})
    assert merge(flat, [rec("a", {"robot_name": "r7"})]).record == {"a.robot_name": "r7", "name": "g",
                                                                   "robot_name": "r7"}  # fmt: skip
    assert "robot_name" not in merge(flat, [rec("a", {"v": 1})]).record


def test_without_tags_or_name_those_keys_are_absent() -> None:
    g = group({"inputs": ["/dc/measurement/a"], "include_group_name": False})
    assert merge(g, [rec("a", {"v": 1, "tags": ["t"]})]).record == {"a": {"v": 1}}


def test_colliding_keys_get_a_suffix_in_inputs_order() -> None:
    g = group({"inputs": ["/r1/cpu", "/r2/cpu", "/r3/cpu", "/x"], "tags": ["t"]})
    merged = merge(
        g,
        [
            rec("cpu", {"v": 1}, "/r1/cpu"),
            rec("cpu", {"v": 2}, "/r2/cpu"),
            rec("cpu", {"v": 3}, "/r3/cpu"),
            rec("tags", {"v": 4}, "/x"),
        ],
    )
    assert merged.record == {"cpu": {"v": 1}, "cpu_2": {"v": 2}, "cpu_3": {"v": 3}, "tags_2": {"v": 4},
                             "tags": ["t"], "name": "g"}  # fmt: skip
    assert merged.renamed == [("cpu", "cpu_2"), ("cpu", "cpu_3"), ("tags", "tags_2")]


def test_partial_record_lists_missing_inputs() -> None:
    g = group({"inputs": ["/dc/measurement/a", "/dc/measurement/b", "/dc/measurement/c"]})
    merged = merge(g, [rec("a", {"v": 1}), None, None])
    assert merged.record == {"a": {"v": 1}, "missing_inputs": ["/dc/measurement/b", "/dc/measurement/c"],
                             "name": "g"}  # fmt: skip


def test_exclude_keys() -> None:
    document = {
        "memory": {"used": 1, "used_percent": 2, "run_id": "3"},
        "uptime": {"time": 4, "run_id": "3"},
        "cams": {"paths": ["a", "b"]},
    }
    assert exclude(document, ["memory.used", "*.run_id", "cams.paths.0"]) == {
        "memory": {"used_percent": 2},
        "uptime": {"time": 4},
        "cams": {"paths": ["b"]},
    }
    assert exclude(document, ["uptime", "memory.*"]) == {"memory": {}, "cams": {"paths": ["a", "b"]}}
    assert document["memory"] == {"used": 1, "used_percent": 2, "run_id": "3"}  # input untouched


def test_flat_output() -> None:
    g = group({"inputs": ["/dc/measurement/a", "/dc/measurement/b"], "nested_data": False, "tags": ["t"],
               "exclude_keys": ["b.skip"]})  # fmt: skip
    merged = merge(g, [rec("a", {"x": {"y": 1}, "l": [1, {"z": 2}], "e": {}}), rec("b", {"skip": 1, "k": 2})])
    assert merged.record == {
        "a.x.y": 1,
        "a.l.0": 1,
        "a.l.1.z": 2,
        "a.e": {},
        "b.k": 2,
        "tags": ["t"],
        "name": "g",
    }
    assert flatten_dotted({}) == {}


def test_group_output_nests_under_the_downstream_group() -> None:
    # The output of one group is an input of another: nested under the first group's group_key.
    inner = group({"inputs": ["/dc/measurement/memory", "/dc/measurement/uptime"], "tags": ["t"]}, "memory_uptime")
    first = merge(inner, [rec("memory", {"used": 1}), rec("uptime", {"time": 2})]).record
    outer = group({"inputs": ["/dc/group/memory_uptime", "/dc/measurement/cpu"], "tags": ["out"]}, "system")
    second = merge(outer, [parse_input("/dc/group/memory_uptime", inner.group_key, json.dumps(first)),
                           rec("cpu", {"usage": 3})])  # fmt: skip
    assert second.record == {
        "memory_uptime": {"memory": {"used": 1}, "uptime": {"time": 2}, "name": "memory_uptime"},
        "cpu": {"usage": 3},
        "tags": ["out"],
        "name": "system",
    }


# -- pipeline --------------------------------------------------------------------------------
def two_input_pipeline(**extra: Any) -> tuple[GroupPipeline, RecordingLogger]:
    logger = RecordingLogger()
    g = group({"inputs": ["/dc/measurement/a", "/dc/measurement/b"], "sync_delay": 0.5, "sync_timeout": 2.0,
               "tags": ["t"], **extra})  # fmt: skip
    return GroupPipeline(g, logger), logger


def test_pipeline_publishes_a_complete_set_stamped_with_its_latest_stamp() -> None:
    pipeline, _ = two_input_pipeline()
    assert pipeline.offer(rec("a", {"v": 1}), 10 * S, now=0.0) == []
    (out,) = pipeline.offer(rec("b", {"w": 2}), 10 * S + S // 10, now=0.1)
    assert out.complete and out.stamp_ns == 10 * S + S // 10 and out.group_key == "g"
    assert json.loads(out.data) == {"a": {"v": 1}, "b": {"w": 2}, "tags": ["t"], "name": "g"}
    assert pipeline.stats()["published"] == 1


def test_pipeline_drops_incomplete_sets_and_logs_the_silent_input_once() -> None:
    pipeline, logger = two_input_pipeline()
    for k in range(4):
        assert pipeline.offer(rec("a", {"v": k}), k * S, now=float(k)) == []
    assert pipeline.expire(now=10.0) == []
    assert pipeline.stats()["dropped_incomplete"] == 4
    warnings = logger.at("warning")
    assert len(warnings) == 1
    assert "/dc/measurement/b" in warnings[0] and "dropped" in warnings[0]
    # b comes back: complete sets flow again, and that is logged.
    pipeline.offer(rec("a", {"v": 9}), 20 * S, now=20.0)
    assert len(pipeline.offer(rec("b", {"w": 9}), 20 * S, now=20.1)) == 1
    assert any("publishes again" in m for m in logger.at("info"))


def test_pipeline_emits_partial_sets_with_the_missing_inputs() -> None:
    pipeline, logger = two_input_pipeline(on_sync_timeout="emit_partial")
    pipeline.offer(rec("a", {"v": 1}), 5 * S, now=0.0)
    assert pipeline.expire(now=1.9) == []
    # The next message's arrival also settles what is due, before it is offered.
    (out,) = pipeline.offer(rec("a", {"v": 2}), 7 * S, now=2.0)
    assert not out.complete and out.stamp_ns == 5 * S
    assert json.loads(out.data) == {
        "a": {"v": 1},
        "missing_inputs": ["/dc/measurement/b"],
        "tags": ["t"],
        "name": "g",
    }
    assert "published without them" in logger.at("warning")[0]
    (last,) = pipeline.flush()
    assert json.loads(last.data)["a"] == {"v": 2}
    assert pipeline.stats()["published_partial"] == 2


def test_pipeline_warns_once_per_renamed_key() -> None:
    logger = RecordingLogger()
    pipeline = GroupPipeline(group({"inputs": ["/r1/cpu", "/r2/cpu"]}), logger)
    for k in range(3):
        pipeline.offer(rec("cpu", {"v": 1}, "/r1/cpu"), k * S, now=float(k))
        (out,) = pipeline.offer(rec("cpu", {"v": 2}, "/r2/cpu"), k * S, now=float(k))
        assert set(json.loads(out.data)) == {"cpu", "cpu_2", "name"}
    assert len([m for m in logger.at("warning") if '"cpu_2"' in m]) == 1
    assert pipeline.stats()["renamed_keys"] == 3
