"""When a measurement publishes: the init phase, condition episodes and their counters.

The rules, decided once here and unit-tested (tests/test_gating.py):

* **Init phase.** ``init_max_measurements = n > 0``: the first ``n`` samples are published whatever
  the conditions say. ``0`` means no init limit: without conditions every sample is published for
  ever; with conditions there is no init phase and the conditions decide from the first sample
  (the original published everything and ignored the conditions here). ``-1``: no init phase.
* **Condition phase** (only when the measurement lists conditions): a sample is published when the
  conditions hold, at most ``condition_max_measurements`` times per episode (an episode is a run of
  consecutive samples for which the conditions hold). ``0`` = unlimited, ``-1`` = never. When the
  conditions stop holding the episode ends and the counter re-arms.
* **Finished.** Nothing more can ever be published (init phase over, and no conditions or
  ``condition_max_measurements = -1``): the measurement's timer is stopped so ``collect()`` is no
  longer called.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class Gate:
    init_max: int
    condition_max: int
    has_conditions: bool
    init_count: int = 0
    episode_count: int = 0

    @property
    def in_init_phase(self) -> bool:
        return self.init_max > 0 and self.init_count < self.init_max

    @property
    def needs_conditions(self) -> bool:
        """True when the next decision depends on the conditions."""
        return self.has_conditions and not self.in_init_phase and not self.finished

    @property
    def finished(self) -> bool:
        if self.in_init_phase:
            return False
        if not self.has_conditions:
            return self.init_max != 0
        return self.condition_max < 0

    def would_admit(self, conditions_met: bool) -> bool:
        """What :meth:`admit` would answer, without changing any counter."""
        if self.finished:
            return False
        if self.in_init_phase or not self.has_conditions:
            return True
        if not conditions_met:
            return False
        return self.condition_max == 0 or self.episode_count < self.condition_max

    def admit(self, conditions_met: bool) -> bool:
        """Decide for one collected sample and advance the counters.

        ``conditions_met`` is ignored while :attr:`needs_conditions` is false.
        """
        if self.finished:
            return False
        if self.in_init_phase:
            self.init_count += 1
            return True
        if not self.has_conditions:
            return True
        if not conditions_met:
            self.episode_count = 0
            return False
        if self.condition_max == 0:
            return True
        if self.episode_count < self.condition_max:
            self.episode_count += 1
            return True
        return False

    def observe_conditions(self, conditions_met: bool) -> None:
        """Record the conditions of a sample that was not collected (the episode may end)."""
        if self.needs_conditions and not conditions_met:
            self.episode_count = 0
