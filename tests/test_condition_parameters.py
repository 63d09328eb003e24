"""Parameters of the built-in conditions: errors that name the YAML path, the original's defaults, bad patterns."""

from __future__ import annotations

from typing import Any

import pytest

from dc_conditions.bool_equal import BoolEqual
from dc_conditions.exist import Exist
from dc_conditions.lists import ListBoolEqual, ListIntegerEqual, ListStringEqual
from dc_conditions.moving import Moving
from dc_conditions.numeric import (
    DoubleEqual,
    DoubleInferior,
    IntegerEqual,
    IntegerSuperior,
)
from dc_conditions.same_as_previous import SameAsPrevious
from dc_conditions.string_match import StringMatch
from dc_core.condition import Condition
from dc_core.errors import ConfigError, PluginError
from dc_core.params import parse_params
from dc_core.testing import FakeContext
from tests.condition_helpers import PATH


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
