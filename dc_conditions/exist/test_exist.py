"""Exist: whether a key path is present in the sample, through objects and arrays."""

from __future__ import annotations

from typing import Any

import pytest

from dc_conditions.exist import Exist
from dc_core.condition import Condition
from tests.condition_helpers import BARCODES, Inactive, check, configured

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
]


@pytest.mark.parametrize(("cls", "params", "sample", "expected"), CASES)
def test_condition(cls: type[Condition[Any]], params: dict[str, Any], sample: Any, expected: bool | Inactive) -> None:
    check(configured(cls, params), sample, expected)
