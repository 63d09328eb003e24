"""StringMatch: a full match of the regular expression, compiled at configure."""

from __future__ import annotations

from typing import Any

import pytest

from dc_conditions.string_match import StringMatch
from dc_core.condition import Condition
from tests.condition_helpers import BARCODES, Inactive, check, configured

CASES: list[Any] = [
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
