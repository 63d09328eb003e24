"""When an incident is recorded: triggers, the window they open or extend, cooldown and the hourly limit.

Pure logic on nanosecond times (no ROS), driven by the Recorder: ``trigger()`` for each trigger
(a condition's rising edge, a service call), ``due()`` at each poll to take the incident whose
window closed. A trigger while a window is open extends it to ``trigger + post`` (one file, every
reason kept); one within ``cooldown`` after a window closed, or past ``max_per_hour`` incidents in
the last hour, is counted and not recorded.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from enum import Enum

HOUR_NS = 3600 * 10**9


class Outcome(Enum):
    OPENED = "opened"
    EXTENDED = "extended"
    COOLDOWN = "cooldown"
    RATE_LIMITED = "rate_limited"


@dataclass(frozen=True)
class Trigger:
    time_ns: int
    reason: str


@dataclass
class Incident:
    start_ns: int
    end_ns: int
    triggers: list[Trigger] = field(default_factory=list)


class Windows:
    def __init__(self, pre_ns: int, post_ns: int, cooldown_ns: int, max_per_hour: int) -> None:
        self.pre_ns = pre_ns
        self.post_ns = post_ns
        self.cooldown_ns = cooldown_ns
        self.max_per_hour = max_per_hour
        self.open: Incident | None = None
        self._cooldown_until = -1
        self._opened_at: deque[int] = deque()
        self.triggers = 0
        self.in_cooldown = 0
        self.over_hourly_limit = 0

    def trigger(self, now_ns: int, reason: str) -> Outcome:
        self.triggers += 1
        if self.open is not None:
            self.open.triggers.append(Trigger(now_ns, reason))
            self.open.end_ns = max(self.open.end_ns, now_ns + self.post_ns)
            return Outcome.EXTENDED
        if now_ns < self._cooldown_until:
            self.in_cooldown += 1
            return Outcome.COOLDOWN
        while self._opened_at and self._opened_at[0] <= now_ns - HOUR_NS:
            self._opened_at.popleft()
        if len(self._opened_at) >= self.max_per_hour:
            self.over_hourly_limit += 1
            return Outcome.RATE_LIMITED
        self._opened_at.append(now_ns)
        self.open = Incident(now_ns - self.pre_ns, now_ns + self.post_ns, [Trigger(now_ns, reason)])
        return Outcome.OPENED

    def due(self, now_ns: int) -> Incident | None:
        """The open incident if its window has closed by ``now_ns`` (then the cooldown starts)."""
        incident = self.open
        if incident is None or now_ns < incident.end_ns:
            return None
        self.open = None
        self._cooldown_until = incident.end_ns + self.cooldown_ns
        return incident
