"""Condition plugins judged on hand-made samples: params + sample -> active, inactive or why not."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from dc_conditions.bool_equal import BoolEqual
from dc_conditions.exist import Exist
from dc_conditions.lists import ListBoolEqual, ListDoubleEqual, ListIntegerEqual, ListStringEqual
from dc_conditions.moving import Moving, MovingHysteresis
from dc_conditions.numeric import (
    DoubleEqual,
    DoubleInferior,
    DoubleSuperior,
    IntegerEqual,
    IntegerInferior,
    IntegerSuperior,
)
from dc_conditions.same_as_previous import SameAsPrevious
from dc_conditions.string_match import StringMatch
from dc_core.condition import Condition
from dc_core.errors import ConfigError, PluginError
from dc_core.params import parse_params
from dc_core.testing import FakeContext

PATH = "measurement_server.c"


@dataclass(frozen=True)
class Inactive:
    """Expected outcome: evaluate raises one of the documented errors, its message containing ``reason``."""

    reason: str


def configured(cls: type[Condition[Any]], params: dict[str, Any]) -> Condition[Any]:
    condition = cls(FakeContext(name="c"), parse_params(cls.Params, params, PATH))
    condition.on_configure()
    return condition


def check(condition: Condition[Any], sample: Any, expected: bool | Inactive) -> None:
    if isinstance(expected, Inactive):
        with pytest.raises((LookupError, TypeError, ValueError)) as caught:
            condition.evaluate(sample)
        assert expected.reason in str(caught.value)
    else:
        assert condition.evaluate(sample) is expected


BARCODES = {"inspected": {"barcode": [{"data": "QR-1", "ok": True}, {"data": "QR-2", "ok": False}]}}

CASES: list[Any] = [
    # Exist: any value counts, null included; arrays are addressed by index.
    pytest.param(Exist, {"key": "inspected"}, BARCODES, True, id="exist-object"),
    pytest.param(Exist, {"key": "inspected/barcode/1/data"}, BARCODES, True, id="exist-through-array"),
    pytest.param(Exist, {"key": "inspected/barcode/2"}, BARCODES, False, id="exist-index-out-of-range"),
    pytest.param(Exist, {"key": "time"}, {"time": 12}, True, id="exist-scalar"),
    pytest.param(Exist, {"key": "time"}, {"time": 0}, True, id="exist-zero"),
    pytest.param(Exist, {"key": "a"}, {"a": None}, True, id="exist-null"),
    pytest.param(Exist, {"key": "a"}, {"a": {}}, True, id="exist-empty-object"),
    pytest.param(Exist, {"key": "a"}, {"a": []}, True, id="exist-empty-array"),
    pytest.param(Exist, {"key": "a/b"}, {"a": 1}, False, id="exist-through-scalar"),
    pytest.param(Exist, {"key": "missing"}, {"a": 1}, False, id="exist-missing"),
    pytest.param(Exist, {"key": "/a/"}, {"a": 1}, True, id="exist-leading-slash"),
    # BoolEqual: only a JSON bool qualifies.
    pytest.param(BoolEqual, {"key": "ok", "value": True}, {"ok": True}, True, id="bool-true"),
    pytest.param(BoolEqual, {"key": "ok", "value": False}, {"ok": False}, True, id="bool-false"),
    pytest.param(BoolEqual, {"key": "ok", "value": True}, {"ok": False}, False, id="bool-differs"),
    pytest.param(BoolEqual, {"key": "ok", "value": True}, {"ok": 1}, Inactive("not a bool"), id="bool-vs-int"),
    pytest.param(BoolEqual, {"key": "ok", "value": True}, {"ok": "true"}, Inactive("not a bool"), id="bool-vs-string"),
    pytest.param(BoolEqual, {"key": "inspected/barcode/1/ok", "value": False}, BARCODES, True, id="bool-in-array"),
    pytest.param(BoolEqual, {"key": "ok", "value": True}, {}, Inactive("'ok'"), id="bool-missing"),
    # DoubleEqual: integers and floats compare as numbers; bools are not numbers.
    pytest.param(DoubleEqual, {"key": "v", "value": 3.5}, {"v": 3.5}, True, id="double-eq-float"),
    pytest.param(DoubleEqual, {"key": "v", "value": 3.0}, {"v": 3}, True, id="double-eq-int-value"),
    pytest.param(DoubleEqual, {"key": "v", "value": 3}, {"v": 3}, True, id="double-eq-int-param"),
    pytest.param(DoubleEqual, {"key": "v", "value": 3.0}, {"v": 3.1}, False, id="double-eq-differs"),
    pytest.param(DoubleEqual, {"key": "v", "value": 1.0}, {"v": True}, Inactive("not a number"), id="double-eq-bool"),
    pytest.param(
        DoubleEqual, {"key": "v", "value": 1.0}, {"v": "1.0"}, Inactive("not a number"), id="double-eq-string"
    ),
    pytest.param(DoubleEqual, {"key": "v", "value": 1.0}, {"v": None}, Inactive("not a number"), id="double-eq-null"),
    pytest.param(DoubleEqual, {"key": "v", "value": 1.0}, {"v": [1.0]}, Inactive("not a number"), id="double-eq-list"),
    pytest.param(DoubleEqual, {"key": "v", "value": 1.0}, {"w": 1.0}, Inactive("'v'"), id="double-eq-missing"),
    # DoubleInferior / DoubleSuperior with and without include_value.
    pytest.param(DoubleInferior, {"key": "v", "value": 20.0}, {"v": 19.9}, True, id="double-inf-below"),
    pytest.param(DoubleInferior, {"key": "v", "value": 20.0}, {"v": 20}, True, id="double-inf-equal-int"),
    pytest.param(
        DoubleInferior,
        {"key": "v", "value": 20.0, "include_value": False},
        {"v": 20.0},
        False,
        id="double-inf-equal-excluded",
    ),
    pytest.param(DoubleInferior, {"key": "v", "value": 20.0}, {"v": 20.1}, False, id="double-inf-above"),
    pytest.param(DoubleInferior, {"key": "v", "value": 0.0}, {"v": -5}, True, id="double-inf-negative-int"),
    pytest.param(
        DoubleSuperior,
        {"key": "battery/percent", "value": 20.0},
        {"battery": {"percent": 85}},
        True,
        id="double-sup-nested-int",
    ),
    pytest.param(DoubleSuperior, {"key": "v", "value": 20.0}, {"v": 20.0}, True, id="double-sup-equal"),
    pytest.param(
        DoubleSuperior,
        {"key": "v", "value": 20.0, "include_value": False},
        {"v": 20},
        False,
        id="double-sup-equal-excluded",
    ),
    pytest.param(DoubleSuperior, {"key": "v", "value": 20.0}, {"v": 19}, False, id="double-sup-below"),
    pytest.param(
        DoubleSuperior,
        {"key": "v", "value": 0.5},
        {"v": False},
        Inactive("not a number"),
        id="double-sup-bool",
    ),
    # IntegerEqual: positive integers work (the original's unsigned bug); 3.0 is 3; 3.5 is not an integer.
    pytest.param(IntegerEqual, {"key": "v", "value": 3}, {"v": 3}, True, id="int-eq-positive"),
    pytest.param(IntegerEqual, {"key": "v", "value": 0}, {"v": 0}, True, id="int-eq-zero"),
    pytest.param(IntegerEqual, {"key": "v", "value": -3}, {"v": -3}, True, id="int-eq-negative"),
    pytest.param(IntegerEqual, {"key": "v", "value": 3}, {"v": 4}, False, id="int-eq-differs"),
    pytest.param(IntegerEqual, {"key": "v", "value": 3}, {"v": 3.0}, True, id="int-eq-integral-float"),
    pytest.param(IntegerEqual, {"key": "v", "value": 3}, {"v": 3.5}, Inactive("not an integer"), id="int-eq-fraction"),
    pytest.param(
        IntegerEqual,
        {"key": "v", "value": 1},
        {"v": True},
        Inactive("not a number"),
        id="int-eq-bool-is-not-1",
    ),
    pytest.param(IntegerEqual, {"key": "v", "value": 2**63}, {"v": 2**63}, True, id="int-eq-beyond-int64"),
    pytest.param(
        IntegerEqual,
        {"key": "v", "value": 1},
        {"v": float("nan")},
        Inactive("not an integer"),
        id="int-eq-nan",
    ),
    pytest.param(IntegerEqual, {"key": "list/1", "value": 7}, {"list": [5, 7]}, True, id="int-eq-array-item"),
    # IntegerInferior / IntegerSuperior.
    pytest.param(IntegerInferior, {"key": "v", "value": 10}, {"v": 9}, True, id="int-inf-below"),
    pytest.param(IntegerInferior, {"key": "v", "value": 10}, {"v": 10}, True, id="int-inf-equal"),
    pytest.param(
        IntegerInferior,
        {"key": "v", "value": 10, "include_value": False},
        {"v": 10},
        False,
        id="int-inf-equal-excluded",
    ),
    pytest.param(IntegerInferior, {"key": "v", "value": 10}, {"v": 11}, False, id="int-inf-above"),
    pytest.param(IntegerInferior, {"key": "v", "value": 10}, {"v": 9.0}, True, id="int-inf-integral-float"),
    pytest.param(
        IntegerInferior,
        {"key": "v", "value": 10},
        {"v": 9.5},
        Inactive("not an integer"),
        id="int-inf-fraction",
    ),
    pytest.param(IntegerSuperior, {"key": "time", "value": 60}, {"time": 3600}, True, id="int-sup-uptime"),
    pytest.param(IntegerSuperior, {"key": "v", "value": 10}, {"v": 10}, True, id="int-sup-equal"),
    pytest.param(
        IntegerSuperior,
        {"key": "v", "value": 10, "include_value": False},
        {"v": 10},
        False,
        id="int-sup-equal-excluded",
    ),
    pytest.param(IntegerSuperior, {"key": "v", "value": 10}, {"v": 9}, False, id="int-sup-below"),
    pytest.param(IntegerSuperior, {"key": "v", "value": 0}, {"v": "5"}, Inactive("not a number"), id="int-sup-string"),
    pytest.param(IntegerSuperior, {"key": "v", "value": 0}, None, Inactive("no sample"), id="int-sup-no-sample"),
    # List* conditions: the key names an array (the original never found it).
    pytest.param(ListIntegerEqual, {"key": "ids", "value": [1, 2, 3]}, {"ids": [1, 2, 3]}, True, id="list-int-ordered"),
    pytest.param(
        ListIntegerEqual,
        {"key": "ids", "value": [1, 2, 3]},
        {"ids": [3, 2, 1]},
        False,
        id="list-int-order-differs",
    ),
    pytest.param(
        ListIntegerEqual,
        {"key": "ids", "value": [1, 2, 3], "order_matters": False},
        {"ids": [3, 1, 2]},
        True,
        id="list-int-unordered",
    ),
    pytest.param(
        ListIntegerEqual,
        {"key": "ids", "value": [1, 1, 2], "order_matters": False},
        {"ids": [1, 2, 2]},
        False,
        id="list-int-unordered-duplicates-differ",
    ),
    pytest.param(
        ListIntegerEqual,
        {"key": "ids", "value": [1, 1, 2], "order_matters": False},
        {"ids": [2, 1, 1]},
        True,
        id="list-int-unordered-duplicates-same",
    ),
    pytest.param(
        ListIntegerEqual,
        {"key": "ids", "value": [1, 2], "order_matters": False},
        {"ids": [1, 2, 2]},
        False,
        id="list-int-unordered-longer",
    ),
    pytest.param(
        ListIntegerEqual,
        {"key": "ids", "value": [1, 2]},
        {"ids": [1.0, 2.0]},
        True,
        id="list-int-integral-floats",
    ),
    pytest.param(
        ListIntegerEqual,
        {"key": "ids", "value": [1, 2]},
        {"ids": [1, 2.5]},
        Inactive("item 1"),
        id="list-int-fraction-item",
    ),
    pytest.param(
        ListIntegerEqual,
        {"key": "ids", "value": [1, 0]},
        {"ids": [True, False]},
        Inactive("not a number"),
        id="list-int-bools",
    ),
    pytest.param(
        ListIntegerEqual,
        {"key": "ids", "value": [1]},
        {"ids": 1},
        Inactive("not an array"),
        id="list-int-scalar",
    ),
    pytest.param(ListIntegerEqual, {"key": "ids", "value": []}, {"ids": []}, True, id="list-int-empty"),
    pytest.param(
        ListIntegerEqual,
        {"key": "a/0/ids", "value": [4]},
        {"a": [{"ids": [4]}]},
        True,
        id="list-int-inside-array",
    ),
    pytest.param(
        ListDoubleEqual, {"key": "xy", "value": [1.5, 2.0]}, {"xy": [1.5, 2]}, True, id="list-double-int-item"
    ),
    pytest.param(
        ListDoubleEqual,
        {"key": "xy", "value": [1.5, 2.0], "order_matters": False},
        {"xy": [2, 1.5]},
        True,
        id="list-double-unordered",
    ),
    pytest.param(
        ListDoubleEqual,
        {"key": "xy", "value": [1.5, 2.0], "order_matters": False},
        {"xy": [2.0, 2.0]},
        False,
        id="list-double-unordered-differs",
    ),
    pytest.param(
        ListDoubleEqual,
        {"key": "xy", "value": [1.0]},
        {"xy": ["1.0"]},
        Inactive("item 0"),
        id="list-double-string-item",
    ),
    pytest.param(
        ListBoolEqual,
        {"key": "f", "value": [True, False]},
        {"f": [True, False]},
        True,
        id="list-bool-ordered",
    ),
    pytest.param(
        ListBoolEqual,
        {"key": "f", "value": [True, False]},
        {"f": [1, 0]},
        Inactive("not a bool"),
        id="list-bool-ints",
    ),
    pytest.param(
        ListBoolEqual,
        {"key": "f", "value": [True, True, False], "order_matters": False},
        {"f": [False, True, True]},
        True,
        id="list-bool-unordered",
    ),
    pytest.param(
        ListBoolEqual,
        {"key": "f", "value": [True, True, False], "order_matters": False},
        {"f": [False, False, True]},
        False,
        id="list-bool-unordered-counts",
    ),
    pytest.param(
        ListStringEqual,
        {"key": "tags", "value": ["a", "b"]},
        {"tags": ["a", "b"]},
        True,
        id="list-string-ordered",
    ),
    pytest.param(
        ListStringEqual,
        {"key": "tags", "value": ["a", "b"], "order_matters": False},
        {"tags": ["b", "a"]},
        True,
        id="list-string-unordered",
    ),
    pytest.param(
        ListStringEqual,
        {"key": "tags", "value": ["1"]},
        {"tags": [1]},
        Inactive("not a string"),
        id="list-string-number-item",
    ),
    pytest.param(ListStringEqual, {"key": "tags", "value": ["a"]}, {}, Inactive("'tags'"), id="list-string-missing"),
    # StringMatch: the whole string must match.
    pytest.param(
        StringMatch,
        {"key": "name", "regex": "robot-[0-9]+"},
        {"name": "robot-42"},
        True,
        id="string-full-match",
    ),
    pytest.param(
        StringMatch,
        {"key": "name", "regex": "robot-[0-9]+"},
        {"name": "my robot-42"},
        False,
        id="string-partial-is-not-a-match",
    ),
    pytest.param(
        StringMatch,
        {"key": "name", "regex": "robot"},
        {"name": "robot-42"},
        False,
        id="string-prefix-is-not-a-match",
    ),
    pytest.param(StringMatch, {"key": "name", "regex": ".*"}, {"name": ""}, True, id="string-empty"),
    pytest.param(
        StringMatch,
        {"key": "inspected/barcode/0/data", "regex": "QR-\\d"},
        BARCODES,
        True,
        id="string-in-array",
    ),
    pytest.param(
        StringMatch,
        {"key": "n", "regex": "4.*"},
        {"n": 42},
        Inactive("not a string"),
        id="string-number-value",
    ),
    pytest.param(
        StringMatch,
        {"key": "n", "regex": ".*"},
        {"n": None},
        Inactive("not a string"),
        id="string-null-value",
    ),
    pytest.param(StringMatch, {"key": "n", "regex": ".*"}, {}, Inactive("'n'"), id="string-missing"),
]


@pytest.mark.parametrize(("cls", "params", "sample", "expected"), CASES)
def test_condition(cls: type[Condition[Any]], params: dict[str, Any], sample: Any, expected: bool | Inactive) -> None:
    check(configured(cls, params), sample, expected)


def test_unordered_comparison_leaves_the_parameter_untouched() -> None:
    condition = configured(ListIntegerEqual, {"key": "ids", "value": [3, 1, 2], "order_matters": False})
    assert condition.evaluate({"ids": [1, 2, 3]}) is True
    assert condition.params.value == [3, 1, 2]


@pytest.mark.parametrize(
    ("cls", "params", "bad_path", "message"),
    [
        pytest.param(Exist, {}, "key", "required", id="exist-no-key"),
        pytest.param(BoolEqual, {"key": "k", "value": 1}, "value", "expected a boolean", id="bool-int-value"),
        pytest.param(BoolEqual, {"key": "k"}, "value", "required", id="bool-no-value"),
        pytest.param(DoubleEqual, {"key": "k", "value": "high"}, "value", "expected a number", id="double-string"),
        pytest.param(
            DoubleInferior,
            {"key": "k", "value": 1.0, "include_value": 3},
            "include_value",
            "expected a boolean",
            id="double-include-int",
        ),
        pytest.param(IntegerEqual, {"key": "k", "value": 2.5}, "value", "expected an integer", id="int-float"),
        pytest.param(IntegerSuperior, {"key": "k", "value": True}, "value", "expected an integer", id="int-bool"),
        pytest.param(IntegerEqual, {"key": "k", "value": 1, "vaule": 2}, "vaule", "did you mean", id="int-typo"),
        pytest.param(
            ListIntegerEqual,
            {"key": "k", "value": 3},
            "value",
            "expected a list of integer",
            id="list-not-a-list",
        ),
        pytest.param(
            ListIntegerEqual,
            {"key": "k", "value": [1, 2.5]},
            "value[1]",
            "expected an integer",
            id="list-int-float-item",
        ),
        pytest.param(
            ListBoolEqual,
            {"key": "k", "value": [True, 2]},
            "value[1]",
            "expected a boolean",
            id="list-bool-int-item",
        ),
        pytest.param(
            ListStringEqual,
            {"key": "k", "value": ["a"], "order_matters": "maybe"},
            "order_matters",
            "expected a boolean",
            id="list-order-not-bool",
        ),
        pytest.param(StringMatch, {"key": "k"}, "regex", "required", id="string-no-regex"),
        pytest.param(SameAsPrevious, {"keys": "path"}, "keys", "expected a list", id="same-keys-not-list"),
        pytest.param(Moving, {"speed_threshold": -1.0}, "speed_threshold", ">= 0", id="moving-negative-speed"),
        pytest.param(Moving, {"count_limit": 0}, "count_limit", ">= 1", id="moving-zero-limit"),
        pytest.param(
            Moving,
            {"count_hysteresis": 2.5},
            "count_hysteresis",
            "expected an integer",
            id="moving-float-hysteresis",
        ),
    ],
)
def test_parameter_errors_name_the_yaml_path(
    cls: type[Condition[Any]], params: dict[str, Any], bad_path: str, message: str
) -> None:
    with pytest.raises(ConfigError) as caught:
        parse_params(cls.Params, params, PATH)
    assert caught.value.path == f"{PATH}.{bad_path}"
    assert message in caught.value.message


def test_parameter_defaults_follow_the_original() -> None:
    moving: Any = parse_params(Moving.Params, {}, PATH)
    assert (moving.odom_topic, moving.speed_threshold, moving.count_limit, moving.count_hysteresis) == (
        "/odom",
        0.2,
        8,
        5,
    )
    assert parse_params(DoubleInferior.Params, {"key": "k", "value": 1}, PATH).include_value is True
    assert parse_params(IntegerSuperior.Params, {"key": "k", "value": 1}, PATH).include_value is True
    assert parse_params(ListStringEqual.Params, {"key": "k", "value": ["a"]}, PATH).order_matters is True


@pytest.mark.parametrize(
    ("cls", "params", "where"),
    [
        pytest.param(StringMatch, {"key": "k", "regex": "([a-z]"}, "c.regex", id="string-bad-regex"),
        pytest.param(SameAsPrevious, {"exclude": ["ok", "*stamp"]}, "c.exclude[1]", id="same-bad-exclude"),
    ],
)
def test_bad_regex_fails_configure(cls: type[Condition[Any]], params: dict[str, Any], where: str) -> None:
    condition = cls(FakeContext(name="c"), parse_params(cls.Params, params, PATH))
    with pytest.raises(PluginError, match=r"invalid regular expression") as caught:
        condition.on_configure()
    assert str(caught.value).startswith(where)


# SameAsPrevious: stateful, so each case is a sequence of samples and the expected answer to each.


def write(path: Path, content: str) -> str:
    path.write_text(content)
    return str(path)


def test_same_as_previous_first_sample_is_never_the_same() -> None:
    condition = configured(SameAsPrevious, {})
    assert [condition.evaluate({"a": 1}) for _ in range(3)] == [False, True, True]


@pytest.mark.parametrize(
    ("params", "samples", "expected"),
    [
        pytest.param({}, [{"a": 1}, {"a": 2}, {"a": 2}, {"a": 1}], [False, False, True, False], id="value-changes"),
        pytest.param({}, [{"a": 1}, {"a": 1.0}], [False, True], id="int-and-float-are-the-same-number"),
        pytest.param({}, [{"a": 1}, {"a": True}], [False, False], id="bool-is-not-1"),
        pytest.param({}, [{"a": [1, 2]}, {"a": [2, 1]}], [False, False], id="array-order-matters"),
        pytest.param({}, [{"a": 1}, {"a": 1, "b": 2}], [False, False], id="new-key"),
        pytest.param({}, [{"a": 1, "tags": ["x"]}, {"a": 1, "tags": ["y"]}], [False, True], id="tags-ignored"),
        pytest.param(
            {"exclude": ["stamp"]},
            [{"a": 1, "stamp": 1}, {"a": 1, "stamp": 2}],
            [False, True],
            id="exclude-top-level",
        ),
        pytest.param(
            {"exclude": ["meta"]},
            [{"a": 1, "meta": {"t": 1}}, {"a": 1, "meta": {"t": 2, "u": 3}}],
            [False, True],
            id="exclude-object-and-its-children",
        ),
        pytest.param(
            {"exclude": ["cams/[0-9]+/stamp"]},
            [
                {"cams": [{"id": 1, "stamp": 1}]},
                {"cams": [{"id": 1, "stamp": 9}]},
                {"cams": [{"id": 2, "stamp": 9}]},
            ],
            [False, True, False],
            id="exclude-regex-through-array",
        ),
        pytest.param(
            {"exclude": ["stamp"]},
            [{"a": {"stamp": 1}}, {"a": {"stamp": 2}}],
            [False, False],
            id="exclude-is-a-full-match-of-the-path",
        ),
        pytest.param(
            {"exclude": [".*stamp"]},
            [{"a": {"stamp": 1}}, {"a": {"stamp": 2}}],
            [False, True],
            id="exclude-pattern-for-any-depth",
        ),
    ],
)
def test_same_as_previous_sequences(
    params: dict[str, Any], samples: list[dict[str, Any]], expected: list[bool]
) -> None:
    condition = configured(SameAsPrevious, params)
    assert [condition.evaluate(s) for s in samples] == expected


def test_same_as_previous_compares_file_contents_not_names(tmp_path: Path) -> None:
    condition = configured(SameAsPrevious, {"keys": ["local_paths/inspected"], "exclude": ["date"]})

    def sample(path: str) -> dict[str, Any]:
        return {"local_paths": {"inspected": path}, "date": path}

    first = write(tmp_path / "a.jpg", "line 1\nsame last line\n")
    assert condition.evaluate(sample(first)) is False
    renamed = write(tmp_path / "b.jpg", "line 1\nsame last line\n")
    assert condition.evaluate(sample(renamed)) is True, "same content under a new name is the same"
    write(tmp_path / "b.jpg", "line 1 changed\nsame last line\n")
    assert condition.evaluate(sample(renamed)) is False, "content changed in place (not on the last line)"
    assert condition.evaluate(sample(renamed)) is True


def test_same_as_previous_file_key_through_an_array_with_negative_index(tmp_path: Path) -> None:
    condition = configured(SameAsPrevious, {"keys": ["/frames/-1/path/"]})
    same = "image bytes"
    assert condition.evaluate({"frames": [{"path": write(tmp_path / "1.jpg", same)}]}) is False
    assert condition.evaluate({"frames": [{"path": write(tmp_path / "2.jpg", same)}]}) is True
    assert condition.evaluate({"frames": [{"path": write(tmp_path / "3.jpg", "other bytes")}]}) is False


def test_same_as_previous_large_file_is_hashed_whole(tmp_path: Path) -> None:
    condition = configured(SameAsPrevious, {"keys": ["file"]})
    big = os.urandom(3 * (1 << 20) + 7)
    path = tmp_path / "big.bin"
    path.write_bytes(big)
    assert condition.evaluate({"file": str(path)}) is False
    path.write_bytes(big[:100] + bytes([big[100] ^ 1]) + big[101:])
    assert condition.evaluate({"file": str(path)}) is False
    assert condition.evaluate({"file": str(path)}) is True


@pytest.mark.parametrize(
    ("sample", "reason"),
    [
        pytest.param({"other": 1}, "'file'", id="key-missing"),
        pytest.param({"file": 3}, "not a string", id="path-not-a-string"),
        pytest.param({"file": "/nonexistent/dc/file"}, "cannot read file", id="file-missing"),
        pytest.param(None, "no sample", id="no-sample"),
    ],
)
def test_same_as_previous_bad_data_is_inactive_and_keeps_the_previous_sample(
    tmp_path: Path, sample: Any, reason: str
) -> None:
    condition = configured(SameAsPrevious, {"keys": ["file"]})
    good = {"file": write(tmp_path / "f.txt", "x")}
    assert condition.evaluate(good) is False
    check(condition, sample, Inactive(reason))
    assert condition.evaluate(good) is True


def test_same_as_previous_starts_over_after_cleanup() -> None:
    condition = configured(SameAsPrevious, {})
    assert condition.evaluate({"a": 1}) is False
    condition.on_cleanup()
    condition.on_configure()
    assert condition.evaluate({"a": 1}) is False


# Moving: the pure hysteresis on hand-made speed sequences.

FAST, SLOW = 1.0, 0.0


@pytest.mark.parametrize(
    ("speeds", "expected_states"),
    [
        pytest.param([FAST] * 4, [False] * 4, id="four-fast-not-yet"),
        pytest.param([FAST] * 5, [False] * 4 + [True], id="fifth-fast-activates"),
        pytest.param(
            [FAST] * 12 + [SLOW] * 13,
            [False] * 4 + [True] * 8 + [True] * 12 + [False],
            id="counter-clamped-to-limit",
        ),
        pytest.param(
            [FAST] * 5 + [SLOW] * 10 + [FAST] * 9,
            [False] * 4 + [True] * 10 + [False] + [False] * 9,
            id="hysteresis-both-ways",
        ),
        pytest.param([FAST, SLOW] * 10, [False] * 20, id="jitter-stays-inactive"),
        pytest.param([0.2] * 10, [False] * 10, id="threshold-is-strict"),
        pytest.param([0.21] * 5, [False] * 4 + [True], id="just-above-threshold"),
    ],
)
def test_moving_hysteresis(speeds: list[float], expected_states: list[bool]) -> None:
    hysteresis = MovingHysteresis(speed_threshold=0.2, count_limit=8, count_hysteresis=5)
    assert [hysteresis.update(s) for s in speeds] == expected_states
    assert -8 <= hysteresis.counter <= 8


def test_moving_hysteresis_keeps_state_between_thresholds() -> None:
    hysteresis = MovingHysteresis(speed_threshold=0.2, count_limit=8, count_hysteresis=5)
    for _ in range(8):
        hysteresis.update(FAST)
    for _ in range(12):  # 8 down to -4: still active
        hysteresis.update(SLOW)
    assert (hysteresis.counter, hysteresis.active) == (-4, True)
    for _ in range(10):
        hysteresis.update(SLOW)
    assert (hysteresis.counter, hysteresis.active) == (-8, False)
    for _ in range(12):  # climbs from -8 to 4: still inactive
        hysteresis.update(FAST)
        if hysteresis.counter == 4:
            break
    assert hysteresis.active is False
    assert hysteresis.update(FAST) is True


@pytest.mark.parametrize(("limit", "hysteresis"), [(8, 9), (3, 0)])
def test_moving_rejects_a_hysteresis_it_could_never_reach(limit: int, hysteresis: int) -> None:
    with pytest.raises(ValueError, match="count_hysteresis"):
        MovingHysteresis(speed_threshold=0.2, count_limit=limit, count_hysteresis=hysteresis)


def test_moving_without_ros_node_fails_configure() -> None:
    condition = Moving(FakeContext(name="c"), parse_params(Moving.Params, {}, PATH))
    with pytest.raises(PluginError, match="ROS node"):
        condition.on_configure()
    assert condition.evaluate(None) is False


def test_moving_hysteresis_above_limit_fails_configure() -> None:
    condition = Moving(
        FakeContext(name="c", node=object()),
        parse_params(Moving.Params, {"count_limit": 4, "count_hysteresis": 5}, PATH),
    )
    with pytest.raises(PluginError, match=r"^c\.count_hysteresis"):
        condition.on_configure()
