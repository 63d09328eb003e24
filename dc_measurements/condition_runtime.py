"""Conditions at run time: safe evaluation, the optional `topic` input, state publication."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

from dc_core.condition import Condition
from dc_core.logs import Logger
from dc_core.records import MalformedRecord, parse_record


class ConditionRuntime:
    """One configured condition, shared by every measurement that lists it."""

    def __init__(
        self, name: str, condition: Condition[Any], topic: str, logger: Logger, publish_state: Callable[[bool], None]
    ) -> None:
        self.name = name
        self.condition = condition
        self.topic = topic
        self._logger = logger
        self._publish_state = publish_state
        self._latest: Mapping[str, Any] | None = None
        self._state: bool | None = None
        self._last_reason = ""
        # Whether the condition could ever judge what it was given: until it could, the first
        # failure is a warning (a key the records never have gates everything, silently else).
        self._evaluated_once = False
        self._failure_warned = False

    @property
    def needs_sample(self) -> bool:
        """True when the condition judges the measurement's own sample (collect must run first)."""
        return self.condition.needs_sample and not self.topic

    @property
    def state(self) -> bool:
        return bool(self._state)

    def on_topic_record(self, data: str) -> None:
        """Latest record of the condition's own `topic`."""
        try:
            self._latest = parse_record(data)
        except MalformedRecord as exc:
            self._logger.debug(f"condition {self.name}: record on {self.topic} ignored: {exc}")

    def evaluate(self, sample: Mapping[str, Any] | None) -> bool:
        """Active now? Never raises: missing or malformed data means inactive, said at debug level."""
        if self.topic:
            judged = self._latest
            if judged is None:
                return self._set(False, f"no record received on {self.topic} yet")
        elif self.condition.needs_sample:
            judged = sample
        else:
            judged = None
        try:
            active = bool(self.condition.evaluate(judged))
        except Exception as exc:  # a condition never crashes the server
            reason = f"{type(exc).__name__}: {exc}"
            if not self._evaluated_once and not self._failure_warned:
                self._failure_warned = True
                keys = ", ".join(map(str, judged)) if isinstance(judged, Mapping) else "no record"
                self._logger.warning(
                    f"condition {self.name} cannot judge the record it is given ({reason}; the record's keys: "
                    f"{keys}): it counts as inactive; said once, then at debug level"
                )
            return self._set(False, reason)
        self._evaluated_once = True
        return self._set(active, "")

    def _set(self, active: bool, reason: str) -> bool:
        if reason and reason != self._last_reason:
            self._logger.debug(f"condition {self.name} inactive: {reason}")
        self._last_reason = reason
        if active != self._state:
            self._state = active
            self._publish_state(active)
        return active


def already_unmet(all_of: list[str], none_of: list[str], states: Mapping[str, bool]) -> bool:
    """Whether the conditions judged so far (``states``, the others unknown) rule a sample out whatever the
    rest say: an if_all condition inactive, or an if_none condition active."""
    return any(states.get(c) is False for c in all_of) or any(states.get(c) is True for c in none_of)


def conditions_met(all_of: list[str], any_of: list[str], none_of: list[str], states: Mapping[str, bool]) -> bool:
    """if_all: every one active; if_any: at least one (when listed); if_none: none active."""
    if not all(states[c] for c in all_of):
        return False
    if any_of and not any(states[c] for c in any_of):
        return False
    return not any(states[c] for c in none_of)
