"""Measurement server logic without ROS: config, run id, custom params, paths, record building, conditions."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from dc_core.errors import ConfigError
from dc_core.measurement import Measurement
from dc_core.paths import expand_env, expand_time, expand_values
from dc_core.records import parse_record
from dc_core.testing import FakeContext, RecordingLogger
from dc_measurements.condition_runtime import ConditionRuntime, conditions_met
from dc_measurements.config import RunIdParams, parse_measurement_server
from dc_measurements.metadata import next_run_id, resolve_custom_params
from dc_measurements.runner import MeasurementRunner
from dc_measurements.uptime import Uptime
from dc_measurements.validation import RecordValidator, schema_version

LOG = RecordingLogger("test")


def server(
    measurements: dict[str, dict[str, Any]], conditions: dict[str, dict[str, Any]] | None = None, **node: Any
) -> dict[str, Any]:
    section: dict[str, Any] = {"measurement_plugins": list(measurements), **node}
    section.update(measurements)
    if conditions:
        section["condition_plugins"] = list(conditions)
        section.update(conditions)
    return section


def make_runner(
    body: dict[str, Any],
    conditions: dict[str, dict[str, Any]] | None = None,
    run_id: str | None = "7",
    custom: list[tuple[str, str, bool]] | None = None,
    samples: list[dict[str, Any] | None] | None = None,
    clock_ns: Any = None,
    schema_version: int | None = None,
    plugin_class: type[Measurement[Any]] | None = None,
) -> tuple[MeasurementRunner, list[tuple[str, str, int | None]]]:
    cfg = parse_measurement_server(server({"m": body}, conditions))
    mcfg = cfg.measurements[0]
    plugin = (plugin_class or mcfg.plugin_class)(FakeContext(), mcfg.plugin_params)
    plugin.on_configure()
    if samples is not None:
        queue = list(samples)
        plugin.collect = lambda: queue.pop(0)
    runtimes = {
        name: ConditionRuntime(
            name, c.plugin_class(FakeContext(), c.plugin_params), c.common.topic, LOG, lambda s: None
        )
        for name, c in cfg.conditions.items()
    }
    schema = plugin.load_schema()
    validator = RecordValidator(schema, "test") if schema and mcfg.common.enable_validator else None
    published: list[tuple[str, str, int | None]] = []
    runner = MeasurementRunner(
        mcfg,
        plugin,
        runtimes,
        validator,
        run_id,
        custom or [],
        lambda text, key, stamp: published.append((text, key, stamp)),
        LOG,
        **({"clock_ns": clock_ns} if clock_ns else {}),
        schema_version=schema_version,
    )
    return runner, published


def records(published: list[tuple[str, str, int | None]]) -> list[dict[str, Any]]:
    return [json.loads(text) for text, _, _ in published]


def test_uptime_record_has_metadata_and_no_flags() -> None:
    runner, published = make_runner({"plugin": "dc_measurements/Uptime", "tags": ["flb_stdout"]})
    runner.tick()
    (record,) = records(published)
    assert set(record) == {"time", "run_id", "tags", "name"}
    assert record["run_id"] == "7" and record["tags"] == ["flb_stdout"] and record["name"] == "m"
    assert abs(record["time"] - float(Path("/proc/uptime").read_text().split()[0])) < 2


def test_a_record_says_the_version_of_its_schema() -> None:
    runner, published = make_runner(
        {"plugin": "dc_measurements/Uptime"}, schema_version=schema_version(Uptime.load_schema())
    )
    runner.tick()
    (record,) = records(published)
    assert record["schema_version"] == 1, "a plugin's schema without a version is its first"
    assert schema_version({"version": 3, "$id": "https://x/cpu/v2"}) == 3
    assert schema_version({"$id": "https://example.com/schemas/cpu/v2"}) == 2
    assert schema_version({"$id": "https://example.com/schemas/cpu/4.json"}) == 4
    assert schema_version(None) is None, "no schema (StringStamped forwards others' records): no key"


@pytest.mark.parametrize("shape", [{}, {"nested": True}, {"flatten": True}])
def test_samples_parsed_from_json_are_written_as_json_writes_them(
    monkeypatch: pytest.MonkeyPatch, shape: dict[str, Any]
) -> None:
    # samples_are_parsed_json lets orjson write the record: the texts must be json's, to the byte.
    texts = [
        '{"small":1e-05,"tiny":1.5e-09,"plain":0.1,"whole":2.0,"neg":-0.0}',
        '{"big":18446744073709551616,"u64":18446744073709551615,"exp":1e300}',
        r'{"text":"\u00e9\u4e2d\ud83d\ude00 \\ \" \u0001 \u007f \u2028","e-":"1e-5","zeros":"0.00001"}',
        r'{"deep":{"list":[1,[2,{"x":null}],true,false],"empty":{}},"k\u00e9y":[]}',
    ]
    written = []
    for parsed in (False, True):
        monkeypatch.setattr(Uptime, "samples_are_parsed_json", parsed)
        runner, published = make_runner(
            {"plugin": "dc_measurements/Uptime", "tags": ["t"], "enable_validator": False, **shape},
            samples=[parse_record(t) for t in texts],
        )
        for _ in texts:
            runner.tick()
        written.append([text for text, _, _ in published])
    assert len(written[0]) == len(texts)
    assert written[1] == written[0]


def test_nested_flatten_plugin_and_custom_params() -> None:
    runner, published = make_runner(
        {
            "plugin": "dc_measurements/Dummy",
            "record": '{"a": {"b": 1}, "robot": "x"}',
            "nested": True,
            "flatten": True,
            "include_measurement_plugin": True,
            "include_measurement_name": False,
        },
        custom=[("robot", "C3PO", False), ("site", "lyon", False), ("name", "forced", True)],
    )
    runner.tick()
    (record,) = records(published)
    assert record == {
        "/m/a/b": 1,
        "/m/robot": "x",
        "nested": True,
        "flattened": True,
        "run_id": "7",
        "plugin": "dc_measurements/Dummy",
        "robot": "C3PO",
        "site": "lyon",
        "name": "forced",
    }


def test_custom_param_does_not_override_without_force() -> None:
    runner, published = make_runner(
        {"plugin": "dc_measurements/Dummy", "record": '{"robot": "R2"}'}, custom=[("robot", "C3PO", False)]
    )
    runner.tick()
    assert records(published)[0]["robot"] == "R2"


def test_invalid_record_is_published_and_hook_called_unless_drop_invalid() -> None:
    calls: list[str] = []
    for drop in (False, True):
        runner, published = make_runner(
            {"plugin": "dc_measurements/Uptime", "drop_invalid": drop}, samples=[{"time": "late"}]
        )
        runner.plugin.on_failed_validation = lambda record, error: calls.append(error)  # type: ignore[method-assign]
        runner.tick()
        assert len(published) == (0 if drop else 1)
        assert runner.stats.invalid == 1
    assert calls and "time" in calls[0]


def test_empty_samples_are_not_published_and_do_not_count() -> None:
    runner, published = make_runner(
        {"plugin": "dc_measurements/Uptime", "init_max_measurements": 2},
        samples=[None, {}, {"time": 1}, None, {"time": 2}, {"time": 3}],
    )
    for _ in range(6):
        runner.tick()
    assert [r["time"] for r in records(published)] == [1, 2]
    assert runner.finished and runner.stats.empty == 3


def test_collect_exception_is_logged_and_counted() -> None:
    runner, published = make_runner({"plugin": "dc_measurements/Uptime"})

    def broken() -> dict[str, Any]:
        raise OSError("gone")

    runner.plugin.collect = broken  # type: ignore[method-assign]
    runner.tick()
    assert published == [] and runner.stats.errors == 1


def test_conditions_gate_on_the_raw_sample_and_are_evaluated_once() -> None:
    runner, published = make_runner(
        {"plugin": "dc_measurements/Dummy", "if_all_conditions": ["has_a", "has_a"], "if_none_conditions": ["has_b"]},
        conditions={
            "has_a": {"plugin": "dc_conditions/Exist", "key": "a"},
            "has_b": {"plugin": "dc_conditions/Exist", "key": "b"},
        },
        samples=[{"a": 1}, {"c": 1}, {"a": 1, "b": 1}, {"a": 2}],
    )
    evaluations: list[str] = []
    for name, runtime in runner._conditions.items():
        original = runtime.evaluate

        def counting(sample: Any, original: Any = original, name: str = name) -> bool:
            evaluations.append(name)
            return bool(original(sample))

        runtime.evaluate = counting  # type: ignore[method-assign]
    for _ in range(4):
        runner.tick()
    assert [r.get("a") for r in records(published)] == [1, 2]
    assert evaluations.count("has_a") == 4 and evaluations.count("has_b") == 4


def test_on_published_is_called_for_published_samples_only() -> None:
    # Files a record points to are written in on_published (Camera): never for a sample that was dropped.
    runner, published = make_runner(
        {"plugin": "dc_measurements/Uptime", "if_all_conditions": ["has_time"], "drop_invalid": True},
        conditions={"has_time": {"plugin": "dc_conditions/Exist", "key": "time"}},
        samples=[{"time": 1}, {"other": 1}, {"time": 2}, {"time": "late"}],
    )
    seen: list[dict[str, Any]] = []
    runner.plugin.on_published = seen.append  # type: ignore[method-assign,assignment]
    for _ in range(4):
        runner.tick()
    # Gated ({"other": 1}) and invalid (time is not an integer, drop_invalid) samples get no call.
    assert seen == [{"time": 1}, {"time": 2}]
    assert [r["time"] for r in records(published)] == [1, 2]

    def broken(sample: dict[str, Any]) -> None:
        raise OSError("disk gone")

    runner.plugin.on_published = broken  # type: ignore[method-assign]
    runner.plugin.collect = lambda: {"time": 4}  # type: ignore[method-assign]
    runner.tick()
    assert len(published) == 3 and runner.stats.errors == 1  # published, and the failure counted


def test_a_sample_the_conditions_without_it_already_rule_out_is_not_collected() -> None:
    # A camera gated by if_none_conditions: [moving] and an Exist on what it reads: while the robot moves
    # the frame is not even read; when it stands, Moving is judged once per sample, not twice.
    runner, published = make_runner(
        {"plugin": "dc_measurements/Dummy", "if_all_conditions": ["has_a"], "if_none_conditions": ["moving"]},
        conditions={
            "has_a": {"plugin": "dc_conditions/Exist", "key": "a"},
            "moving": {"plugin": "dc_conditions/Moving"},
        },
        samples=[{"a": 1}, {"a": 2}, {"a": 3}],
    )
    moving_runtime = runner._conditions["moving"]
    moving_state = [True]
    judged: list[str] = []

    def moving(sample: Any) -> bool:
        judged.append("moving")
        return moving_state[0]

    moving_runtime.evaluate = moving  # type: ignore[method-assign]
    collected: list[int] = []
    original_collect = runner.plugin.collect

    def counting_collect() -> Any:
        sample = original_collect()
        assert sample is not None
        collected.append(sample["a"])
        return sample

    runner.plugin.collect = counting_collect  # type: ignore[method-assign]
    runner.tick()
    assert collected == [] and published == [] and runner.stats.gated == 1
    moving_state[0] = False
    judged.clear()
    runner.tick()
    assert collected == [1] and [r["a"] for r in records(published)] == [1]
    assert judged == ["moving"]  # once for this sample


def test_a_frame_taken_before_the_conditions_held_is_not_the_one_published() -> None:
    # The QR-code camera: the newest frame at the poll that first sees the robot standing may have been
    # taken while it still moved. It is skipped (not counted against condition_max_measurements) and
    # the next poll's newer frame is the episode's record.
    now = [10_000]
    runner, published = make_runner(
        {
            "plugin": "dc_measurements/Dummy",
            "if_all_conditions": ["has_a"],
            "if_none_conditions": ["moving"],
            "init_max_measurements": -1,
            "condition_max_measurements": 1,
        },
        conditions={
            "has_a": {"plugin": "dc_conditions/Exist", "key": "a"},
            "moving": {"plugin": "dc_conditions/Moving"},
        },
        clock_ns=lambda: now[0],
    )
    moving = [True]
    runner._conditions["moving"].evaluate = lambda sample: moving[0]  # type: ignore[method-assign]
    frames = [({"a": 1}, 9_000), ({"a": 2}, 10_500), ({"a": 3}, 10_700), ({"a": 4}, 10_200)]
    runner.plugin.collect_stamped = lambda: (*frames.pop(0), None)  # type: ignore[method-assign]
    runner.tick()  # moving: nothing read
    moving[0] = False
    runner.tick()  # standing since 10_000: the frame of 9_000 predates it
    assert published == [] and runner.stats.gated == 2
    runner.tick()  # a frame of 10_500: the episode's one record
    runner.tick()  # condition_max_measurements: 1
    assert [(r["a"], stamp) for r, (_, _, stamp) in zip(records(published), published, strict=True)] == [(2, 10_500)]
    moving[0] = True
    runner.tick()
    moving[0] = False
    now[0] = 10_600
    runner.tick()  # a new episode from 10_600: the frame of 10_200 (read late) predates it too
    assert len(published) == 1


def test_conditions_met_truth_table() -> None:
    states = {"a": True, "b": False}
    assert conditions_met([], [], [], states)
    assert conditions_met(["a"], [], ["b"], states)
    assert not conditions_met(["a", "b"], [], [], states)
    assert conditions_met([], ["a", "b"], [], states)
    assert not conditions_met([], ["b"], [], states)
    assert not conditions_met([], [], ["a"], states)


def test_condition_runtime_never_raises_and_publishes_changes_only() -> None:
    cfg = parse_measurement_server(
        server({}, {"c": {"plugin": "dc_conditions/IntegerSuperior", "key": "v", "value": 3}})
    )
    c = cfg.conditions["c"]
    states: list[bool] = []
    rt = ConditionRuntime("c", c.plugin_class(FakeContext(), c.plugin_params), "", LOG, states.append)
    assert rt.evaluate({"v": 5}) and rt.evaluate({"v": 9})
    assert not rt.evaluate({"v": "five"})
    assert not rt.evaluate({})
    assert rt.evaluate({"v": 4})
    assert states == [True, False, True]


def test_condition_with_topic_judges_the_other_topic() -> None:
    cfg = parse_measurement_server(
        server(
            {},
            {
                "c": {
                    "plugin": "dc_conditions/DoubleSuperior",
                    "key": "percent",
                    "value": 20.0,
                    "topic": "/dc/measurement/battery",
                }
            },
        )
    )
    c = cfg.conditions["c"]
    rt = ConditionRuntime("c", c.plugin_class(FakeContext(), c.plugin_params), c.common.topic, LOG, lambda s: None)
    assert not rt.needs_sample
    assert not rt.evaluate({"percent": 99})  # nothing received on the topic yet
    rt.on_topic_record('{"percent": 50}')
    assert rt.evaluate(None)
    rt.on_topic_record("not json")
    assert rt.evaluate(None)
    rt.on_topic_record('{"percent": 10}')
    assert not rt.evaluate({"percent": 99})


@pytest.mark.parametrize(
    ("section", "message"),
    [
        (
            server({"u": {"plugin": "dc_measurements/Uptim"}}),
            "measurement_server.u.plugin: unknown measurement plugin 'dc_measurements/Uptim' (did you mean \"dc_measurements/Uptime\"?)",
        ),
        (
            server({"u": {"plugin": "dc_measurements/Uptime", "polling_interval": "fast"}}),
            'measurement_server.u.polling_interval: expected an integer, got "fast"',
        ),
        (
            server({"u": {"plugin": "dc_measurements/Uptime", "if_all_conditions": ["moving"]}}),
            "measurement_server.u.if_all_conditions: condition 'moving' is not in condition_plugins",
        ),
        ({"measurement_plugins": ["u"]}, "measurement_server.u: section missing"),
        (
            {**server({"u": {"plugin": "dc_measurements/Uptime"}}), "uptim": {}},
            "measurement_server.uptim: unknown parameter",
        ),
        (
            server({"u": {"plugin": "dc_measurements/Uptime"}}, run_id={"counter": True, "uuid": True}),
            "measurement_server.run_id: choose one source",
        ),
        (
            server({"d": {"plugin": "dc_measurements/Dummy", "record": "[1]"}}),
            "measurement_server.d.record: expected a JSON object",
        ),
        (
            server(
                {
                    "a": {"plugin": "dc_measurements/Uptime"},
                    "b": {"plugin": "dc_measurements/Uptime", "topic_output": "/dc/measurement/a"},
                }
            ),
            "measurement_server.b.topic_output: /dc/measurement/a is already the output of 'a'",
        ),
        (
            server({}, custom_str_params_list=["robot"], custom_str_params={"robot": {"name": "robot"}}),
            "measurement_server.custom_str_params.robot: needs 'value' or 'value_from_file'",
        ),
        (
            server({"u": {"plugin": "dc_measurements/Uptime"}}, http_port=-1),
            "measurement_server.http_port: expected an integer >= 0",
        ),
    ],
)
def test_configuration_errors(section: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_measurement_server(section)
    assert str(info.value).startswith(message)


def test_run_id_counter_increments_and_uuid(tmp_path: Path) -> None:
    counter = tmp_path / "deep" / "run_id"
    params = RunIdParams(counter_path=str(counter))
    assert next_run_id(params) == "1"
    assert next_run_id(params) == "2"
    assert counter.read_text().strip() == "2"
    uid = next_run_id(RunIdParams(counter=False, uuid=True))
    assert uid is not None and len(uid) == 36
    assert next_run_id(RunIdParams(enabled=False)) is None
    counter.write_text("garbage")
    with pytest.raises(ConfigError, match="does not hold an integer"):
        next_run_id(params)


def test_custom_params_from_value_and_file(tmp_path: Path) -> None:
    machine = tmp_path / "machine-id"
    machine.write_text("abc123\n")
    cfg = parse_measurement_server(
        server(
            {},
            custom_str_params_list=["robot_name", "id"],
            custom_str_params={
                "robot_name": {"name": "robot_name", "value": "C3PO"},
                "id": {"name": "id", "value_from_file": str(machine), "force_override": True},
            },
        )
    )
    assert resolve_custom_params(cfg.custom_str_params) == [("robot_name", "C3PO", False), ("id", "abc123", True)]
    machine.unlink()
    with pytest.raises(ConfigError, match=r"custom_str_params\.id\.value_from_file: cannot read"):
        resolve_custom_params(cfg.custom_str_params)


def test_path_expansion() -> None:
    env = {"HOME": "/home/robot", "ROBOT": "r2"}
    assert expand_env("$HOME/data/${ROBOT}_x", environ=env) == "/home/robot/data/r2_x"
    with pytest.raises(ConfigError, match=r"\$NOPE is not set"):
        expand_env("$NOPE/x", "measurement_server.save_local_base_path", environ=env)
    assert expand_values("base/=robot/={site}", {"robot": "C3PO", "site": "lyon"}.get) == "base/C3PO/lyon"
    with pytest.raises(ConfigError, match="'=missing' names no string parameter"):
        expand_values("=missing", lambda name: None)
    assert expand_time("%Y-%m-%dT%H", when=0) == "1970-01-01T00"


def test_a_condition_that_remembers_samples_shared_by_two_measurements_is_warned_about() -> None:
    same = {"plugin": "dc_conditions/SameAsPrevious"}
    shared = parse_measurement_server(
        server(
            {
                "a": {"plugin": "dc_measurements/Uptime", "if_all_conditions": ["same"]},
                "b": {"plugin": "dc_measurements/Uptime", "if_none_conditions": ["same"]},
            },
            {"same": same},
        )
    )
    assert any("measurement_server.same:" in w and "a, b all use it" in w for w in shared.warnings)
    alone = parse_measurement_server(
        server({"a": {"plugin": "dc_measurements/Uptime", "if_all_conditions": ["same"]}}, {"same": same})
    )
    assert alone.warnings == []


def test_a_condition_that_cannot_judge_its_records_says_so_once() -> None:
    c = server(
        {"u": {"plugin": "dc_measurements/Uptime"}},
        {"c": {"plugin": "dc_conditions/IntegerSuperior", "key": "tme", "value": 1}},
    )
    config = parse_measurement_server(c)
    (ccfg,) = config.conditions.values()
    logger = RecordingLogger()
    states: list[bool] = []
    rt = ConditionRuntime("c", ccfg.plugin_class(FakeContext(), ccfg.plugin_params), "", logger, states.append)
    for time_s in (5, 6, 7):
        assert rt.evaluate({"time": time_s}) is False
    (warning,) = logger.at("warning")
    assert "condition c cannot judge the record it is given" in warning
    assert "'tme'" in warning and "the record's keys: time" in warning
    assert len(logger.at("debug")) == 1, "later failures with the same reason stay quiet"
    assert states == [False]


class TriggeredUptime(Uptime):
    """Uptime whose conditions are its trigger, as the Recorder's: it notes each poll's verdict."""

    conditions_trigger = True
    schema_file = None  # (its module is a test's, with no schema beside it)

    def __init__(self, context: Any, params: Any) -> None:
        super().__init__(context, params)
        self.polls: list[bool | None] = []

    def on_poll(self, conditions_met: bool | None) -> None:
        self.polls.append(conditions_met)


def test_a_conditions_trigger_measurement_is_polled_with_the_verdict_and_its_records_are_not_gated() -> None:
    runner, published = make_runner(
        {"plugin": "dc_measurements/Uptime", "if_all_conditions": ["low"], "condition_max_measurements": 1},
        {"low": {"plugin": "dc_conditions/DoubleInferior", "key": "percent", "value": 20.0, "topic": "/battery"}},
        plugin_class=TriggeredUptime,
    )
    plugin = runner.plugin
    assert isinstance(plugin, TriggeredUptime)
    runner.tick()  # nothing received on /battery: not met
    runner._conditions["low"].on_topic_record('{"percent": 10}')
    runner.tick()
    runner._conditions["low"].on_topic_record('{"percent": 50}')
    runner.tick()
    assert plugin.polls == [False, True, False]
    assert published == [], "polled, never collected"
    # What it emits is published whatever the conditions say now, past condition_max_measurements.
    runner.emit({"time": 1.0})
    runner.emit({"time": 2.0})
    assert [r["time"] for r in records(published)] == [1.0, 2.0]
