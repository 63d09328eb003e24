"""The gating state machine: init phase, condition episodes, counters (dc_core/gating.py)."""

from __future__ import annotations

import pytest

from dc_core.gating import Gate


def run(gate: Gate, conditions: list[bool]) -> list[bool]:
    return [gate.admit(c) for c in conditions]


def test_defaults_without_conditions_publish_forever() -> None:
    gate = Gate(init_max=0, condition_max=0, has_conditions=False)
    assert run(gate, [False] * 50) == [True] * 50
    assert not gate.finished


def test_init_max_without_conditions_publishes_n_then_finishes() -> None:
    gate = Gate(init_max=3, condition_max=0, has_conditions=False)
    assert run(gate, [False] * 5) == [True, True, True, False, False]
    assert gate.finished


def test_init_max_minus_one_without_conditions_never_publishes() -> None:
    gate = Gate(init_max=-1, condition_max=0, has_conditions=False)
    assert gate.finished
    assert run(gate, [True, True]) == [False, False]


def test_conditions_are_honoured_with_default_init_max() -> None:
    # The original published everything here and ignored the conditions.
    gate = Gate(init_max=0, condition_max=0, has_conditions=True)
    assert run(gate, [False, True, True, False, True]) == [False, True, True, False, True]


def test_init_phase_ignores_conditions_then_conditions_decide() -> None:
    gate = Gate(init_max=2, condition_max=0, has_conditions=True)
    assert run(gate, [False, False, False, True]) == [True, True, False, True]


@pytest.mark.parametrize(
    ("condition_max", "conditions", "expected"),
    [
        (1, [True, True, True, False, True, True], [True, False, False, False, True, False]),
        (2, [True, True, True, False, False, True, True, True], [True, True, False, False, False, True, True, False]),
        (0, [True, True, False, True], [True, True, False, True]),
    ],
    ids=["one-per-episode", "two-per-episode", "unlimited"],
)
def test_condition_max_counts_per_episode_and_rearms(
    condition_max: int, conditions: list[bool], expected: list[bool]
) -> None:
    gate = Gate(init_max=-1, condition_max=condition_max, has_conditions=True)
    assert run(gate, conditions) == expected


def test_condition_max_minus_one_finishes_after_init() -> None:
    gate = Gate(init_max=2, condition_max=-1, has_conditions=True)
    assert run(gate, [True, True]) == [True, True]
    assert gate.finished
    assert gate.admit(True) is False


def test_would_admit_does_not_change_counters() -> None:
    gate = Gate(init_max=-1, condition_max=1, has_conditions=True)
    assert gate.would_admit(True)
    assert gate.would_admit(True)
    assert gate.admit(True)
    assert not gate.would_admit(True)


def test_observed_false_conditions_end_the_episode() -> None:
    gate = Gate(init_max=-1, condition_max=1, has_conditions=True)
    assert gate.admit(True)
    assert not gate.would_admit(True)
    gate.observe_conditions(False)
    assert gate.would_admit(True)


def test_needs_conditions_only_after_init_phase() -> None:
    gate = Gate(init_max=1, condition_max=0, has_conditions=True)
    assert not gate.needs_conditions
    gate.admit(False)
    assert gate.needs_conditions
