"""List conditions: ordered and unordered comparison, element types."""

from __future__ import annotations

from typing import Any

import pytest

from dc_conditions.lists import ListBoolEqual, ListDoubleEqual, ListIntegerEqual, ListStringEqual
from dc_core.condition import Condition
from tests.condition_helpers import Inactive, check, configured


def test_unordered_comparison_leaves_the_parameter_untouched() -> None:
    condition = configured(ListIntegerEqual, {"key": "ids", "value": [3, 1, 2], "order_matters": False})
    assert condition.evaluate({"ids": [1, 2, 3]}) is True
    assert condition.params.value == [3, 1, 2]


CASES: list[Any] = [
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
]


@pytest.mark.parametrize(("cls", "params", "sample", "expected"), CASES)
def test_condition(cls: type[Condition[Any]], params: dict[str, Any], sample: Any, expected: bool | Inactive) -> None:
    check(configured(cls, params), sample, expected)
