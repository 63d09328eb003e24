"""Moving's hysteresis and configuration, without ROS (test_moving_ros.py feeds it real odometry)."""

from __future__ import annotations

import pytest

from dc_conditions.moving import Moving, MovingHysteresis
from dc_core.errors import PluginError
from dc_core.params import parse_params
from dc_core.testing import FakeContext
from tests.condition_helpers import PATH

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
