"""BoolEqual: only a JSON bool qualifies."""

from __future__ import annotations

from typing import Any

import pytest

from dc_conditions.bool_equal import BoolEqual
from dc_core.condition import Condition
from tests.condition_helpers import BARCODES, Inactive, check, configured

CASES: list[Any] = [
    # BoolEqual: only a JSON bool qualifies.
    pytest.param(BoolEqual, {"key": "ok", "value": True}, {"ok": True}, True, id="bool-true"),
    pytest.param(BoolEqual, {"key": "ok", "value": False}, {"ok": False}, True, id="bool-false"),
    pytest.param(BoolEqual, {"key": "ok", "value": True}, {"ok": False}, False, id="bool-differs"),
    pytest.param(BoolEqual, {"key": "ok", "value": True}, {"ok": 1}, Inactive("not a bool"), id="bool-vs-int"),
    pytest.param(BoolEqual, {"key": "ok", "value": True}, {"ok": "true"}, Inactive("not a bool"), id="bool-vs-string"),
    pytest.param(BoolEqual, {"key": "inspected/barcode/1/ok", "value": False}, BARCODES, True, id="bool-in-array"),
    pytest.param(BoolEqual, {"key": "ok", "value": True}, {}, Inactive("'ok'"), id="bool-missing"),
]


@pytest.mark.parametrize(("cls", "params", "sample", "expected"), CASES)
def test_condition(cls: type[Condition[Any]], params: dict[str, Any], sample: Any, expected: bool | Inactive) -> None:
    check(configured(cls, params), sample, expected)
