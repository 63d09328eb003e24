"""Exponential retry backoff with full jitter (Fluent Bit's ``scheduler.base`` / ``scheduler.cap``).

Full jitter spreads the retries of many robots that lost the same server at the same moment, so
they do not come back in lockstep: the n-th consecutive failure waits a uniform random time in
``[0, min(cap, base * 2**n)]``.
"""

from __future__ import annotations

import random
from collections.abc import Callable


class Backoff:
    def __init__(self, base: float, cap: float, uniform: Callable[[float, float], float] | None = None) -> None:
        self.base = base
        self.cap = cap
        self._uniform = uniform if uniform is not None else random.Random().uniform
        self.failures = 0

    def ceiling(self, failures: int) -> float:
        """Upper bound of the wait after ``failures`` consecutive failures (1 = the first)."""
        exponent = min(max(failures - 1, 0), 64)  # 2**64 * base exceeds any sane cap
        return min(self.cap, self.base * (2.0**exponent))

    def next_delay(self) -> float:
        """Register one more failure and return how long to wait before the next attempt."""
        self.failures += 1
        return self._uniform(0.0, self.ceiling(self.failures))

    def reset(self) -> None:
        self.failures = 0
