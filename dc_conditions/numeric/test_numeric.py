"""Numeric conditions (Double/Integer Equal, Inferior, Superior): numbers compare as numbers, bools are not numbers."""

from __future__ import annotations

from typing import Any

import pytest

from dc_conditions.numeric import (
    DoubleEqual,
    DoubleInferior,
    DoubleSuperior,
    IntegerEqual,
    IntegerInferior,
    IntegerSuperior,
)
from dc_core.condition import Condition
from tests.condition_helpers import Inactive, check, configured

CASES: list[Any] = [
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
]


@pytest.mark.parametrize(("cls", "params", "sample", "expected"), CASES)
def test_condition(cls: type[Condition[Any]], params: dict[str, Any], sample: Any, expected: bool | Inactive) -> None:
    check(configured(cls, params), sample, expected)
