"""dc_core.records: what every server refuses to carry, and what it carries unchanged."""

from __future__ import annotations

import json
from typing import Any

import pytest

from dc_core.records import MalformedRecord, dump_parsed, dump_record, measurement_of, parse_record


@pytest.mark.parametrize(
    ("text", "reason"),
    [
        ("{nope", "invalid JSON"),
        ("[1]", "expected a JSON object, got a JSON array"),
        ('{"a": NaN}', "NaN is not a JSON number"),
        ('{"a": -Infinity}', "-Infinity is not a JSON number"),
        ('{"a": 1e309}', "not finite"),
        ('{"a": ' + "1" + "0" * 309 + ".5}", "not finite"),
        ('{"a": ' + "9" * 5000 + "}", "invalid JSON (Exceeds the limit"),
        ('{"t": "a\\ud800b"}', "lone surrogate \\ud800"),
        ('{"a": ' + "[" * 3000 + "]" * 3000 + "}", "nested too deeply"),
    ],
    ids=["invalid", "array", "nan", "infinity", "exponent", "309-digit-float", "huge-int", "surrogate", "deep"],
)
def test_what_no_server_carries(text: str, reason: str) -> None:
    with pytest.raises(MalformedRecord, match=None) as refused:
        parse_record(text)
    assert reason in str(refused.value)


@pytest.mark.parametrize(
    "record",
    [
        {"a": 1e308, "b": -0.0, "big": 10**300},
        {"pair": "\U0001f600", "nul": "\x00", "quote": '"'},
        {"nested": [[{"k": [1, 2.5, None, True]}]]},
    ],
    ids=["large-but-finite", "unicode-and-controls", "nested"],
)
def test_what_every_server_carries_unchanged(record: dict[str, Any]) -> None:
    text = dump_record(record)
    assert parse_record(text) == record
    assert json.loads(text) == record, "any JSON reader gets the same record"


def test_dump_refuses_what_a_plugin_may_produce() -> None:
    with pytest.raises(MalformedRecord, match="not finite"):
        dump_record({"v": float("nan")})
    with pytest.raises(MalformedRecord, match="lone surrogate"):
        dump_record({"file": "caf\udce9.txt"})  # a file name that is not UTF-8, as os.listdir gives it
    with pytest.raises(MalformedRecord, match="not JSON-serialisable"):
        dump_record({"when": object()})


@pytest.mark.parametrize(
    "text",
    [
        '{"big": 18446744073709551616, "neg": -9223372036854775809}',  # beyond 64 bits: exact, as json reads them
        '{"long": 1234567890123456789012.5}',
        '{"small": [1e-05, 1.5e-09, 7.000749751940372e-05, 0.0001, 2.2e-308]}',  # json's way of writing them
        '{"looks": "0.00001 and 1e-7"}',
        '{"pair": "\\ud83d\\ude00", "escaped": "\\u00e9\\n"}',
        '{"a": 1, "a": 2}',
    ],
    ids=["beyond-64-bits", "long-float", "small-floats", "string-like-small-float", "escapes", "duplicate-key"],
)
def test_fast_path_reads_and_writes_as_json_does(text: str) -> None:
    record = parse_record(text)
    assert record == json.loads(text)
    assert [type(v) for v in record.values()] == [type(v) for v in json.loads(text).values()]
    expected = json.dumps(record, ensure_ascii=False, separators=(",", ":"), allow_nan=False)
    assert dump_parsed(record) == dump_record(record) == expected


def test_fast_path_refuses_with_json_reasons() -> None:
    """What orjson refuses, json reads and the rule refuses: the reason is the rule's, not orjson's."""
    for text, reason in (('{"a": NaN}', "NaN is not a JSON number"), ('{"t": "\\udcff"}', "lone surrogate")):
        with pytest.raises(MalformedRecord) as refused:
            parse_record(text)
        assert reason in str(refused.value)


def test_dump_parsed_writes_what_orjson_cannot() -> None:
    deep: dict[str, Any] = {}
    inner = deep
    for _ in range(300):  # deeper than orjson writes
        inner["a"] = inner = {}
    record = {"big": 10**30, "deep": deep}
    assert dump_parsed(record) == dump_record(record)


def test_the_measurement_a_topic_names_is_its_last_segment() -> None:
    # One rule for destination settings, saved files, InfluxDB, Slack and the group merge.
    assert measurement_of("/dc/measurement/cpu") == "cpu"
    assert measurement_of("/robot1/dc/measurement/camera") == "camera"
    assert measurement_of("dc.r1.cpu") == "dc.r1.cpu"  # a NATS subject without a topic header: whole
    assert measurement_of("/dc/measurement/cpu/") == "cpu"  # no ROS name, but a NATS header may say it
    assert measurement_of("/") == measurement_of("") == ""  # each caller has its own fallback
