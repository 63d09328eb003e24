"""Routing: which destinations receive a record, and what they receive (pure, no ROS)."""

from __future__ import annotations

import itertools
import json
from typing import Any

import pytest

from dc_core.timefmt import format_stamp
from dc_destinations.routing import BAD_TAGS, NO_LISTENER, NO_TAGS, UNTRUSTED, RouteTarget, RoutingTable

STAMP_NS = 1_677_668_906_045_817_000  # 2023-03-01T11:08:26.045817Z: a fraction with a leading zero
STAMP_S = pytest.approx(1677668906.045817, abs=1e-6)


def table(**inputs: list[str]) -> RoutingTable:
    """Destinations named by keyword, each listening on the given topics, time key "date" as double."""
    by_topic: dict[str, list[RouteTarget]] = {}
    for name, topics in inputs.items():
        for topic in topics:
            by_topic.setdefault(topic, []).append(RouteTarget(name, "date", "double"))
    return RoutingTable(by_topic)


def destinations(t: RoutingTable, topic: str, record: dict[str, Any]) -> list[str]:
    return [name for name, _ in t.route(topic, record, STAMP_NS).deliveries]


ROUTING_CASES = [
    # (case id, destinations -> their inputs, topic, tags, expected destinations)
    ("exact match", {"flb_stdout": ["/up"]}, "/up", ["flb_stdout"], ["flb_stdout"]),
    ("substring of a tag does not match", {"flb_pg": ["/up"]}, "/up", ["flb_pgsql"], []),
    ("tag that is a substring does not match", {"flb_pgsql": ["/up"]}, "/up", ["flb_pg"], []),
    ("exact only", {"flb_pg": ["/up"], "flb_pgsql": ["/up"]}, "/up", ["flb_pgsql"], ["flb_pgsql"]),
    ("several destinations", {"a": ["/up"], "b": ["/up"], "c": ["/up"]}, "/up", ["a", "c"], ["a", "c"]),
    ("topic not in the destination's inputs", {"a": ["/other"]}, "/up", ["a"], []),
    ("one listens, the other does not", {"a": ["/up"], "b": ["/other"]}, "/up", ["a", "b"], ["a"]),
    ("duplicate tag delivers once", {"a": ["/up"]}, "/up", ["a", "a"], ["a"]),
    ("unknown tag ignored", {"a": ["/up"]}, "/up", ["a", "nope"], ["a"]),
]


@pytest.mark.parametrize(
    ("inputs", "topic", "tags", "expected"), [c[1:] for c in ROUTING_CASES], ids=[c[0] for c in ROUTING_CASES]
)
def test_routing_table(inputs: dict[str, list[str]], topic: str, tags: list[str], expected: list[str]) -> None:
    assert destinations(table(**inputs), topic, {"tags": tags, "time": 1}) == expected


@pytest.mark.parametrize(
    ("record", "reason"),
    [
        ({"time": 1}, NO_TAGS),
        ({"time": 1, "tags": []}, NO_TAGS),
        ({"time": 1, "tags": [1, 2]}, BAD_TAGS),
        ({"time": 1, "tags": {"a": True}}, BAD_TAGS),
        ({"time": 1, "tags": ["b"]}, NO_LISTENER),
    ],
    ids=["missing", "empty", "not strings", "not a list", "no listener"],
)
def test_unrouted_records_say_why(record: dict[str, Any], reason: str) -> None:
    routed = table(a=["/up"]).route("/up", record, STAMP_NS)
    assert routed.deliveries == []
    assert routed.unrouted_reason == reason


def test_comma_separated_tags_string_is_accepted() -> None:
    # The original joined the tag list with commas before matching; records built that way still route.
    assert destinations(table(a=["/up"], b=["/up"]), "/up", {"tags": "a, b"}) == ["a", "b"]


def test_delivered_record_drops_tags_and_starts_with_the_time_key() -> None:
    stamp_ns = 1_677_668_906_500_000_000
    routed = table(a=["/up"]).route("/up", {"time": 92395, "tags": ["a"], "robot_name": "C3PO"}, stamp_ns)
    ((name, out),) = routed.deliveries
    assert name == "a"
    assert out.topic == "/up"
    assert out.stamp_ns == stamp_ns
    assert list(out.data) == ["date", "time", "robot_name", "record_id"]
    assert out.to_json() == f'{{"date":1677668906.5,"time":92395,"robot_name":"C3PO","record_id":"{out.record_id}"}}'


def test_double_time_prints_as_the_stamp_s_decimal() -> None:
    # The seed's output shows "date":1677668906.745817; stamp_ns / 1e9 prints 1677668906.7458172.
    assert repr(format_stamp(1_677_668_906_745_817_000, "double")) == "1677668906.745817"


@pytest.mark.parametrize(
    ("time_format", "expected"),
    [
        ("double", STAMP_S),
        # Zero-padded: the original wrote the nanoseconds unpadded after the dot (".45817000").
        ("iso8601", "2023-03-01T11:08:26.045817Z"),
    ],
)
def test_time_formats(time_format: str, expected: float | str) -> None:
    t = RoutingTable({"/up": [RouteTarget("a", "date", time_format)]})
    ((_, out),) = t.route("/up", {"tags": ["a"]}, STAMP_NS).deliveries
    assert out.data["date"] == expected


def test_iso8601_with_a_tiny_fraction_is_zero_padded() -> None:
    t = RoutingTable({"/up": [RouteTarget("a", "ts", "iso8601")]})
    ((_, out),) = t.route("/up", {"tags": ["a"]}, 1_700_000_000_000_001_000).deliveries
    assert out.data == {"ts": "2023-11-14T22:13:20.000001Z", "record_id": out.record_id}


def test_each_destination_gets_its_own_time_key_format_and_copy() -> None:
    t = RoutingTable({"/up": [RouteTarget("a", "date", "double"), RouteTarget("b", "@timestamp", "iso8601")]})
    routed = t.route("/up", {"tags": ["a", "b"], "time": 1}, STAMP_NS)
    (a_name, a), (b_name, b) = routed.deliveries
    assert (a_name, b_name) == ("a", "b")
    assert a.data == {"date": STAMP_S, "time": 1, "record_id": a.record_id}
    assert b.data == {"@timestamp": "2023-03-01T11:08:26.045817Z", "time": 1, "record_id": b.record_id}
    assert a.data is not b.data


def test_empty_time_key_adds_no_time() -> None:
    t = RoutingTable({"/up": [RouteTarget("a", "", "double")]})
    ((_, out),) = t.route("/up", {"tags": ["a"], "time": 1}, STAMP_NS).deliveries
    assert out.data == {"time": 1, "record_id": out.record_id}


def test_time_key_replaces_a_record_value_of_the_same_name() -> None:
    ((_, out),) = table(a=["/up"]).route("/up", {"tags": ["a"], "date": "yesterday"}, STAMP_NS).deliveries
    assert out.data == {"date": STAMP_S, "record_id": out.record_id}


def test_a_record_gets_one_id_shared_by_its_destinations_and_kept_in_its_json() -> None:
    counter = itertools.count(1)
    t = table(a=["/up"], b=["/up"])
    routed = t.route("/up", {"tags": ["a", "b"]}, STAMP_NS, new_record_id=lambda: f"id-{next(counter)}")
    assert [r.record_id for _, r in routed.deliveries] == ["id-1", "id-1"]
    assert [r.data["record_id"] for _, r in routed.deliveries] == ["id-1", "id-1"]
    again = t.route("/up", {"tags": ["a"]}, STAMP_NS, new_record_id=lambda: f"id-{next(counter)}")
    assert again.deliveries[0][1].record_id == "id-2"


def test_default_record_ids_are_unique() -> None:
    t = table(a=["/up"])
    ids = {t.route("/up", {"tags": ["a"]}, STAMP_NS).deliveries[0][1].record_id for _ in range(100)}
    assert len(ids) == 100


KEY_ORDER_RECORDS = [
    {"tags": ["a"], "x": 1},
    {"x": 1, "tags": ["a", "b"], "date": "old", "record_id": "theirs"},
    {"record_id": "theirs", "tags": ["b", "a"], "y": [1, {"z": 2}]},
    {"date": 0, "@t": 1, "tags": "a, b"},
]


@pytest.mark.parametrize(
    "time_keys", [("date",), ("",), ("tags",), ("record_id",), ("date", "@t"), ("", ""), ("tags", "")]
)
@pytest.mark.parametrize("record", KEY_ORDER_RECORDS)
def test_what_each_destination_receives_key_by_key_in_order(time_keys: tuple[str, ...], record: dict[str, Any]) -> None:
    """Whatever the time key is called, even after a key of the record: the tags go, the id comes in
    place of a record_id (or last), the time key first or in place of a value of its name, and it wins."""
    names = ["a", "b"][: len(time_keys)]
    t = RoutingTable({"/up": [RouteTarget(n, k, "double") for n, k in zip(names, time_keys, strict=True)]})
    routed = t.route("/up", record, STAMP_NS, new_record_id=lambda: "ours")
    tags = [tag.strip() for tag in record["tags"].split(",")] if isinstance(record["tags"], str) else record["tags"]
    wanted = [n for n in tags if n in names]
    assert [name for name, _ in routed.deliveries] == wanted
    for name, out in routed.deliveries:
        time_key = time_keys[names.index(name)]
        expected: dict[str, Any] = {time_key: None} if time_key else {}
        expected.update((k, v) for k, v in record.items() if k != "tags")
        expected["record_id"] = "ours"
        if time_key:
            expected[time_key] = format_stamp(STAMP_NS, "double")
        assert list(out.data.items()) == list(expected.items())
        assert out.to_json() == json.dumps(expected, separators=(",", ":"))


def test_input_record_is_not_modified() -> None:
    record = {"tags": ["a"], "time": 1}
    table(a=["/up"]).route("/up", record, STAMP_NS)
    assert record == {"tags": ["a"], "time": 1}


def test_topics_and_listeners() -> None:
    t = table(a=["/up", "/cpu"], b=["/cpu"])
    assert t.topics == ["/cpu", "/up"]
    assert t.listeners("/cpu") == ["a", "b"]
    assert t.listeners("/nothing") == []


def test_an_untrusted_record_reaches_only_the_destinations_that_read_no_file() -> None:
    files = RouteTarget("flb_minio", "date", "double", trusted_only=True)
    rows = RouteTarget("flb_pgsql", "date", "double")
    t = RoutingTable({"/dc/measurement/map": [files, rows]})
    record = {"tags": ["flb_minio", "flb_pgsql"], "local_paths": {"pgm": "/root/.ssh/id_rsa"}}
    trusted = t.route("/dc/measurement/map", record, STAMP_NS)
    assert [name for name, _ in trusted.deliveries] == ["flb_minio", "flb_pgsql"] and not trusted.refused
    untrusted = t.route("/dc/measurement/map", record, STAMP_NS, trusted=False)
    assert [name for name, _ in untrusted.deliveries] == ["flb_pgsql"]
    assert untrusted.refused == ["flb_minio"]
    only_files = t.route("/dc/measurement/map", {"tags": ["flb_minio"]}, STAMP_NS, trusted=False)
    assert (only_files.deliveries, only_files.refused, only_files.unrouted_reason) == ([], ["flb_minio"], UNTRUSTED)
    assert t.has_trusted_only("/dc/measurement/map") and not t.has_trusted_only("/other")
